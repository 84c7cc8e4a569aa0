"""Warm start from a LeRobot Diffusion Policy checkpoint (`--policy.init_from`) and the per-slot FiLM
step conditioning (`step_conditioning="film_per_slot"`), which is exactly DP's network at one level."""

import json
import logging
import shutil

import pytest
import torch
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from sdp_test_utils import PUSHT_STATS, history, observation, tiny_config

from lerobot_sdp import SDPPolicy, make_sdp_pre_post_processors
from lerobot_sdp.warm_start import normalizer_stats

MEAN_STD, MIN_MAX = NormalizationMode.MEAN_STD, NormalizationMode.MIN_MAX


def dp_config(sdp_cfg, **overrides):
    """A LeRobot Diffusion Policy config with `sdp_cfg`'s features and network sizes (horizon 16)."""
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    kwargs = dict(
        n_obs_steps=sdp_cfg.n_obs_steps, horizon=16, n_action_steps=4, down_dims=sdp_cfg.down_dims,
        diffusion_step_embed_dim=sdp_cfg.diffusion_step_embed_dim, crop_shape=sdp_cfg.crop_shape,
        pretrained_backbone_weights=None, use_group_norm=True, use_separate_rgb_encoder_per_camera=False,
        spatial_softmax_num_keypoints=sdp_cfg.spatial_softmax_num_keypoints,
        input_features=dict(sdp_cfg.input_features), output_features=dict(sdp_cfg.output_features),
        device="cpu",
    )  # fmt: skip
    kwargs.update(overrides)
    return DiffusionConfig(**kwargs)


def save_dp(path, sdp_cfg, seed=0, processors=False, stats=PUSHT_STATS, **overrides):
    """A trained-looking DP checkpoint folder (random weights, biases too) as lerobot-train writes it:
    config.json + model.safetensors, with `processors` also policy_preprocessor.json + stats."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(seed)
    cfg = dp_config(sdp_cfg, **overrides)
    policy = DiffusionPolicy(cfg)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.1 * torch.randn_like(p))  # no tensor left at its initial value
    policy.save_pretrained(path)
    if processors:
        pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
        pre.save_pretrained(path)
        post.save_pretrained(path)
    return policy.eval()


def dp_input(sdp_cfg, batch_size=3, seed=0):
    """(noisy actions, per-sample level, observation history with stacked cameras)."""
    gen = torch.Generator().manual_seed(seed)
    obs = history(sdp_cfg, batch_size)
    if sdp_cfg.image_features:
        obs["observation.images"] = torch.stack([obs[k] for k in sdp_cfg.image_features], dim=-4)
    x = torch.randn(batch_size, sdp_cfg.horizon, 2, generator=gen)
    t = torch.randint(0, sdp_cfg.num_train_timesteps, (batch_size,), generator=gen)
    return x, t, obs


def unet_outputs(sdp_model, dp_model, x, t, obs):
    """SDP's U-Net with every slot at level t[b] and DP's U-Net at t[b], same input and observation."""
    with torch.no_grad():
        levels = t[:, None].expand(-1, x.shape[1])
        sdp = sdp_model.unet(x, levels, global_cond=sdp_model._prepare_global_conditioning(obs))
        dp = dp_model.unet(x, t, global_cond=dp_model._prepare_global_conditioning(obs))
    return sdp, dp


def test_warm_start_copies_dp_and_reports_what_it_initialised(tmp_path, caplog):
    cfg = tiny_config(image=True, init_from=str(tmp_path))
    dp = save_dp(tmp_path, cfg)
    with caplog.at_level(logging.INFO):
        policy = SDPPolicy(cfg)
    report = policy.warm_start_report
    dp_state = {k.removeprefix("diffusion."): v for k, v in dp.state_dict().items()}
    model_state, ema_state = policy.model.state_dict(), policy.ema_model.state_dict()
    step_encoder = {k for k in model_state if k.startswith("unet.diffusion_step_encoder.")}
    assert set(report.copied) == set(model_state) - step_encoder
    for key in report.copied:
        torch.testing.assert_close(model_state[key], dp_state[key], atol=0, rtol=0)
        torch.testing.assert_close(ema_state[key], dp_state[key], atol=0, rtol=0)
    groups = {k.split(".")[0] if k.startswith("rgb") else ".".join(k.split(".")[:2]) for k in report.copied}
    assert groups == {
        "rgb_encoder",
        "unet.down_modules",
        "unet.mid_modules",
        "unet.up_modules",
        "unet.final_conv",
    }
    assert set(report.initialised) == step_encoder
    assert all("step_conditioning=flatten" in why for why in report.initialised.values())
    assert not report.unused  # DP's step encoder initialised the flattened one
    assert "Warm start from the Diffusion Policy checkpoint" in caplog.text
    assert "initialised 4 tensors (unet.diffusion_step_encoder (4))" in caplog.text
    # the flattened encoder starts from DP's: at one level for every slot, SDP is DP
    sdp_out, dp_out = unet_outputs(policy.eval().model, dp.diffusion, *dp_input(cfg))
    torch.testing.assert_close(sdp_out, dp_out, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("image", [False, True])
@pytest.mark.parametrize(
    "geometry", [dict(), dict(n_action_steps=7), dict(n_chunks=3, num_inference_steps=9)]
)
def test_film_per_slot_is_dp_at_one_level_for_every_slot(tmp_path, image, geometry):
    """Horizons 10, 16 (DP's own) and 14: the film_per_slot U-Net is convolutional like DP's."""
    cfg = tiny_config(image=image, step_conditioning="film_per_slot", init_from=str(tmp_path), **geometry)
    dp = save_dp(tmp_path, cfg)
    policy = SDPPolicy(cfg).eval()
    report = policy.warm_start_report
    assert set(report.copied) == set(policy.model.state_dict()) and not report.initialised
    assert any(k.startswith("unet.diffusion_step_encoder.") for k in report.copied) and not report.unused
    x, t, obs = dp_input(cfg)
    for model in (policy.model, policy.ema_model):
        sdp_out, dp_out = unet_outputs(model, dp.diffusion, x, t, obs)
        torch.testing.assert_close(sdp_out, dp_out, atol=1e-5, rtol=1e-5)


def test_film_per_slot_conditions_each_position_on_its_own_level():
    torch.manual_seed(0)
    cfg = tiny_config(step_conditioning="film_per_slot")
    model = SDPPolicy(cfg).eval().model
    x, _, obs = dp_input(cfg)
    cond = model._prepare_global_conditioning(obs)
    levels = torch.full((3, cfg.horizon), 5)
    with torch.no_grad():
        base = model.unet(x, levels, global_cond=cond)
        late = levels.clone()
        late[:, -2:] = 90  # the last (deepest-level) pair of slots noisier
        changed = model.unet(x, late, global_cond=cond)
    assert not torch.allclose(base, changed)
    policy = SDPPolicy(cfg)
    loss, _ = policy.forward({**history(cfg, 4), "action": torch.rand(4, cfg.horizon, 2)})
    loss.backward()
    assert torch.isfinite(loss) and policy.model.unet.diffusion_step_encoder[1].weight.grad.abs().sum() > 0
    policy.eval()
    actions = [policy.select_action(observation(cfg, seed=i)) for i in range(2 * cfg.n_action_steps + 1)]
    assert all(a.shape == (2, 2) and torch.isfinite(a).all() for a in actions)  # the streaming loop runs


def test_state_dict_keys_per_step_conditioning():
    """Default (paper) keys are unchanged; film_per_slot has exactly DP's U-Net keys."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    flatten = SDPPolicy(tiny_config()).model.state_dict()
    assert {k for k in flatten if "diffusion_step_encoder" in k} == {
        f"unet.diffusion_step_encoder.mlp.{i}.{p}" for i in (0, 2) for p in ("weight", "bias")
    }
    film = SDPPolicy(tiny_config(step_conditioning="film_per_slot")).model.state_dict()
    dp = DiffusionPolicy(dp_config(tiny_config())).state_dict()
    assert set(film) == {k.removeprefix("diffusion.") for k in dp}
    assert set(film) - set(flatten) == {
        f"unet.diffusion_step_encoder.{i}.{p}" for i in (1, 3) for p in ("weight", "bias")
    }


def test_unknown_step_conditioning_is_refused():
    with pytest.raises(ValueError, match="step_conditioning"):
        tiny_config(step_conditioning="per_slot")


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))}), r"actions are .*\(3,\)"),
        (
            dict(down_dims=(16, 64)),
            r"`down_dims` is \(16, 64\) there, \(16, 32\) here.*--policy.down_dims=\[16,64\]",
        ),
        (dict(n_obs_steps=3), r"`n_obs_steps` is 3 there, 2 here.*--policy.n_obs_steps=3"),
        (
            dict(spatial_softmax_num_keypoints=8, use_separate_rgb_encoder_per_camera=True),
            r"keypoints=8 --policy.use_separate_rgb_encoder_per_camera=true \(as the checkpoint\)",
        ),
        ("camera", r"observation features differ \(only in the checkpoint: \['observation.images.wrist'\]"),
        ("act", r"is a 'act' checkpoint, not a LeRobot `diffusion` one"),
        (
            dict(normalization_mapping={"VISUAL": MEAN_STD, "STATE": MIN_MAX, "ACTION": MEAN_STD}),
            r"normalises differently \(ACTION: MEAN_STD there, MIN_MAX here\)",
        ),
    ],
)
def test_checkpoint_that_does_not_fit_is_a_clear_error(tmp_path, change, message):
    cfg = tiny_config(image=True, init_from=str(tmp_path))
    if change == "camera":
        extra = {"observation.images.wrist": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))}
        save_dp(tmp_path, cfg, input_features={**cfg.input_features, **extra})
    elif change == "act":
        save_dp(tmp_path, cfg)
        config = json.loads((tmp_path / "config.json").read_text())
        (tmp_path / "config.json").write_text(json.dumps({**config, "type": "act"}))
    else:
        save_dp(tmp_path, cfg, **change)
    with pytest.raises(ValueError, match=message):
        SDPPolicy(cfg)


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match=r"without config\.json and model\.safetensors"):
        SDPPolicy(tiny_config(init_from=str(tmp_path)))
    with pytest.raises(ValueError, match="neither a checkpoint folder nor a Hub id"):
        SDPPolicy(tiny_config(init_from=str(tmp_path / "not" / "there")))


def test_training_checkpoint_folder_and_hub_id(tmp_path, monkeypatch):
    """A `checkpoints/last` folder holding `pretrained_model/`, and a Hub id through snapshot_download."""
    import huggingface_hub

    pretrained = tmp_path / "last" / "pretrained_model"
    dp = save_dp(pretrained, tiny_config())
    expected = dp.state_dict()["diffusion.unet.final_conv.1.weight"]
    policy = SDPPolicy(tiny_config(init_from=str(tmp_path / "last")))
    torch.testing.assert_close(policy.model.state_dict()["unet.final_conv.1.weight"], expected)

    calls = []

    def fake_snapshot_download(repo_id, **kwargs):
        calls.append(repo_id)
        return str(pretrained)

    monkeypatch.setattr(huggingface_hub, "snapshot_download", fake_snapshot_download)
    policy = SDPPolicy(tiny_config(init_from="someone/dp_pusht"))
    assert calls == ["someone/dp_pusht"] and policy.warm_start_report.source == "someone/dp_pusht"
    torch.testing.assert_close(policy.model.state_dict()["unet.final_conv.1.weight"], expected)


def test_sdp_checkpoint_keeps_its_trained_weights(tmp_path):
    """from_pretrained does not re-run the warm start (the DP checkpoint may even be gone)."""
    dp_dir, sdp_dir = tmp_path / "dp", tmp_path / "sdp"
    cfg = tiny_config(step_conditioning="film_per_slot", init_from=str(dp_dir))
    save_dp(dp_dir, cfg)
    policy = SDPPolicy(cfg)
    with torch.no_grad():
        for p in (*policy.model.parameters(), *policy.ema_model.parameters()):
            p.add_(1.0)  # "training"
    policy.save_pretrained(sdp_dir)
    shutil.rmtree(dp_dir)
    loaded = SDPPolicy.from_pretrained(sdp_dir)
    assert loaded.config.init_from == str(dp_dir) and loaded.warm_start_report is None
    for key, value in policy.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value, atol=0, rtol=0, equal_nan=True)


def test_warm_started_run_normalises_with_the_checkpoints_stats(tmp_path, caplog):
    dp_stats = {
        "observation.state": {
            "min": [0.0, 0.0],
            "max": [100.0, 200.0],
            "mean": [5.0, 6.0],
            "std": [2.0, 3.0],
        },
        "observation.environment_state": {"min": [-1.0] * 16, "max": [1.0] * 16},
        "action": {"min": [0.0, 0.0], "max": [100.0, 200.0], "mean": [5.0, 6.0], "std": [2.0, 3.0]},
    }
    cfg = tiny_config(action_primer="constant", init_from=str(tmp_path))
    save_dp(tmp_path, cfg, processors=True, stats=dp_stats)
    assert normalizer_stats(str(tmp_path))["action"]["max"].tolist() == [100.0, 200.0]
    with caplog.at_level(logging.WARNING):
        preprocess, postprocess = make_sdp_pre_post_processors(cfg, dataset_stats=PUSHT_STATS)
    assert "differ from the checkpoint's" in caplog.text and "'action'" in caplog.text
    raw = {"observation.state": torch.tensor([50.0, 100.0]), "action": torch.tensor([100.0, 0.0])}
    normalised = preprocess({**raw, "observation.environment_state": torch.zeros(16)})
    torch.testing.assert_close(normalised["observation.state"], torch.tensor([[0.0, 0.0]]))
    torch.testing.assert_close(normalised["action"], torch.tensor([[1.0, -1.0]]))
    torch.testing.assert_close(postprocess(torch.tensor([[1.0, -1.0]])), torch.tensor([[100.0, 0.0]]))
    # the constant primer maps state to action with the same (the checkpoint's) statistics
    policy = SDPPolicy(cfg, dataset_stats=PUSHT_STATS)
    torch.testing.assert_close(policy.state_to_action, torch.tensor([[1.0, 1.0], [0.0, 0.0]]))


def test_checkpoint_without_processor_falls_back_to_the_dataset_stats(tmp_path, caplog):
    cfg = tiny_config(init_from=str(tmp_path))
    save_dp(tmp_path, cfg)  # save_pretrained only: no policy_preprocessor.json
    with caplog.at_level(logging.WARNING):
        preprocess, _ = make_sdp_pre_post_processors(cfg, dataset_stats=PUSHT_STATS)
    assert "holds no normaliser statistics" in caplog.text
    raw = {"observation.state": torch.tensor([13.0, 510.0]), "action": torch.tensor([12.0, 25.0])}
    out = preprocess({**raw, "observation.environment_state": torch.zeros(16)})
    torch.testing.assert_close(out["observation.state"], torch.tensor([[-1.0, 1.0]]))


def test_lerobot_train_warm_starts_from_a_trained_dp(tmp_path):
    """Through the real CLI: DP trained for 2 steps by lerobot-train, then `--policy.init_from` (with
    film_per_slot) trains SDP from it; the run logs the report and normalises with DP's statistics."""
    from sdp_test_utils import make_tiny_pusht_dataset
    from test_cli_e2e import BIN, TINY_POLICY, run, train_args

    root = tmp_path / "dataset"
    make_tiny_pusht_dataset(root)
    dp_args = [a for a in train_args(root, tmp_path / "dp", image=False) if not a.startswith("--policy.")]
    dp_policy = [a for a in TINY_POLICY if not a.startswith(("--policy.type", "--policy.noise_schemes"))]
    dp_policy += ["--policy.type=diffusion", "--policy.horizon=16", "--policy.push_to_hub=false"]
    run([str(BIN / "lerobot-train"), *dp_args, *dp_policy])
    dp_dir = tmp_path / "dp" / "checkpoints" / "last" / "pretrained_model"
    sdp_args = train_args(root, tmp_path / "sdp", image=False)
    sdp_args += [f"--policy.init_from={dp_dir}", "--policy.step_conditioning=film_per_slot"]
    log = run([str(BIN / "lerobot-train"), *sdp_args])
    assert "Warm start from the Diffusion Policy checkpoint" in log and "initialised" not in log
    sdp_dir = tmp_path / "sdp" / "checkpoints" / "last" / "pretrained_model"
    dp_stats, sdp_stats = normalizer_stats(dp_dir), normalizer_stats(sdp_dir)
    assert dp_stats.keys() == sdp_stats.keys()
    for key, value in dp_stats.items():
        torch.testing.assert_close(sdp_stats[key], value)
    assert SDPPolicy.from_pretrained(sdp_dir).config.init_from == str(dp_dir)


def test_checkpoint_saved_before_these_options_loads_as_the_paper_network(tmp_path):
    policy = SDPPolicy(tiny_config())
    policy.save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    assert config["step_conditioning"] == "flatten" and config["init_from"] is None
    del config["step_conditioning"], config["init_from"]
    (tmp_path / "config.json").write_text(json.dumps(config))
    loaded = SDPPolicy.from_pretrained(tmp_path)
    assert (
        loaded.config.step_conditioning == "flatten"
        and loaded.state_dict().keys() == policy.state_dict().keys()
    )
