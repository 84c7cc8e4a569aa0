"""SDPPolicy: training loss, EMA, save/load round trip and bad input."""

import json

import pytest
import torch
from sdp_test_utils import PUSHT_STATS, history, observation, tiny_config

from lerobot_sdp import SDPPolicy
from lerobot_sdp.buffer import StreamResetError


def training_batch(cfg, batch_size=4):
    batch = history(cfg, batch_size)
    batch["action"] = torch.rand(batch_size, cfg.horizon, 2) * 2 - 1
    batch["action_is_pad"] = torch.zeros(batch_size, cfg.horizon, dtype=torch.bool)
    return batch


@pytest.mark.parametrize("image", [False, True])
def test_training_step_reduces_loss_on_a_fixed_batch(image):
    torch.manual_seed(0)
    cfg = tiny_config(image=image, prediction_type="sample")
    policy = SDPPolicy(cfg)
    batch = training_batch(cfg)
    optim = torch.optim.Adam(policy.get_optim_params(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss, _ = policy.forward(batch)
        optim.zero_grad()
        loss.backward()
        optim.step()
        policy.update()
        losses.append(loss.item())
    assert sum(losses[-10:]) / 10 < 0.5 * sum(losses[:5]) / 5


def test_padded_actions_do_not_contribute_to_the_loss_when_masked():
    # unweighted (min_snr_gamma=None), so the loss is mean(a^2) over the slots that count
    cfg = tiny_config(prediction_type="sample", do_mask_loss_for_padding=True, min_snr_gamma=None)
    policy = SDPPolicy(cfg)
    policy.model.unet.forward = lambda x, t, global_cond=None: torch.zeros_like(x)
    batch = training_batch(cfg)
    batch["action_is_pad"][:, -6:] = True
    batch["action"][:, -6:] = 100.0  # garbage where padded
    loss, _ = policy.forward(batch)
    torch.testing.assert_close(loss, batch["action"][:, :-6].pow(2).mean())
    policy.config.do_mask_loss_for_padding = False  # the default, as LeRobot's DP: padding counts
    torch.testing.assert_close(policy.forward(batch)[0], batch["action"].pow(2).mean())


def test_ema_follows_the_authors_schedule_and_serves_eval():
    cfg = tiny_config(ema_power=0.75, ema_max_decay=0.9999)
    policy = SDPPolicy(cfg)
    p_model = next(policy.model.unet.parameters())
    p_ema = next(policy.ema_model.unet.parameters())
    before = p_ema.detach().clone()
    with torch.no_grad():
        p_model.add_(1.0)
    policy.update()  # step 0: decay 0 -> EMA copies the weights
    torch.testing.assert_close(p_ema, p_model)
    with torch.no_grad():
        p_model.add_(1.0)
    policy.update()  # step 1: decay 1 - 2**-0.75
    decay = 1 - 2**-0.75
    torch.testing.assert_close(p_ema, decay * (before + 1) + (1 - decay) * p_model)
    assert int(policy.ema_step) == 2
    assert policy.eval()._sampling_model() is policy.ema_model
    assert policy.train()._sampling_model() is policy.model
    assert not any(p is q for p in policy.get_optim_params() for q in policy.ema_model.parameters())


def test_trainer_ema_beside_sdp_ema_never_averages_twice():
    """LeRobot main's `lerobot-train --ema.enable=true` keeps diffusers' EMAModel over
    `policy.parameters()` and swaps its shadow in to evaluate and to save `pretrained_model_ema`.
    SDP's own EMA copy does not require grad, which EMAModel copies instead of averaging: with both
    on, the policy samples from SDP's single EMA of the live weights, never an EMA of that EMA."""
    from diffusers.training_utils import EMAModel

    cfg = tiny_config()
    policy = SDPPolicy(cfg)
    trainer_ema = EMAModel(policy.parameters(), decay=0.9999, use_ema_warmup=True, power=0.75)  # main's call
    optimizer = torch.optim.SGD(policy.get_optim_params(), lr=0.5)
    for _ in range(4):  # lerobot-train's order: optimizer step, policy.update(), then the trainer's EMA
        optimizer.zero_grad()
        policy.forward(training_batch(cfg))[0].backward()
        optimizer.step()
        policy.update()
        trainer_ema.step(policy.parameters())
    sdp_ema = {k: v.clone() for k, v in policy.ema_model.state_dict().items()}
    params = list(policy.parameters())
    trainer_ema.store(params)
    trainer_ema.copy_to(params)  # main's `_ema_weights` context
    assert policy.eval()._sampling_model() is policy.ema_model
    for key, value in policy.ema_model.state_dict().items():
        torch.testing.assert_close(value, sdp_ema[key], atol=0, rtol=0)
    trainer_ema.restore(params)


def test_save_load_round_trip_gives_identical_actions(tmp_path):
    cfg = tiny_config(action_primer="constant")
    policy = SDPPolicy(cfg, dataset_stats=PUSHT_STATS)
    policy.update()
    policy.save_pretrained(tmp_path)
    loaded = SDPPolicy.from_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["type"] == "sdp"
    torch.testing.assert_close(loaded.state_to_action, policy.state_to_action)
    policy.eval()
    actions = []
    for p in (policy, loaded):
        torch.manual_seed(123)
        p.reset()
        actions.append(torch.stack([p.select_action(observation(cfg, seed=i)) for i in range(12)]))
    torch.testing.assert_close(actions[0], actions[1], atol=0, rtol=0)


def test_streaming_state_stays_out_of_the_checkpoint():
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    policy.select_action(observation(cfg))
    assert policy._buffer.sample is not None
    assert not any("buffer" in k or "queue" in k for k in policy.state_dict())


def test_predict_action_chunk_returns_clean_chunk_only():
    cfg = tiny_config()
    chunk = SDPPolicy(cfg).eval().predict_action_chunk(history(cfg, 3))
    assert chunk.shape == (3, cfg.n_action_steps, 2)


@pytest.mark.parametrize("image, n_obs_steps", [(False, 2), (True, 2), (True, 1)])
def test_offline_chunk_on_a_real_dataset_batch(tmp_path, image, n_obs_steps):
    """A `lerobot-train` batch (LeRobotDataset -> DataLoader -> SDP's preprocessor, `task` strings,
    indices and actions included) goes into predict_action_chunk as it goes into LeRobot's DP."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.utils.feature_utils import dataset_to_policy_features
    from sdp_test_utils import make_tiny_pusht_dataset

    from lerobot_sdp import make_sdp_pre_post_processors

    make_tiny_pusht_dataset(tmp_path / "ds", image=image, n_episodes=1, length=24)
    features = dataset_to_policy_features(
        LeRobotDataset("local/tiny_pusht", root=tmp_path / "ds").meta.features
    )
    inputs = {k: ft for k, ft in features.items() if k.startswith("observation.")}
    cfg = tiny_config(
        n_obs_steps=n_obs_steps,
        crop_shape=(84, 84) if image else None,
        input_features=inputs,
        output_features={"action": features["action"]},
    )
    meta = LeRobotDataset("local/tiny_pusht", root=tmp_path / "ds").meta
    ds = LeRobotDataset(
        "local/tiny_pusht", root=tmp_path / "ds", delta_timestamps=resolve_delta_timestamps(cfg, meta)
    )
    preprocess, _ = make_sdp_pre_post_processors(cfg, meta.stats)
    batch = preprocess(next(iter(torch.utils.data.DataLoader(ds, batch_size=3))))
    assert isinstance(batch["task"][0], str) and "action" in batch and "index" in batch
    if image and n_obs_steps == 1:  # a single-frame image without its time axis, as DP accepts it
        batch["observation.image"] = batch["observation.image"][:, 0]
    chunk = SDPPolicy(cfg, dataset_stats=meta.stats).eval().predict_action_chunk(batch)
    assert chunk.shape == (3, cfg.n_action_steps, 2) and torch.isfinite(chunk).all()
    dp_cfg = DiffusionConfig(
        n_obs_steps=n_obs_steps, horizon=16, n_action_steps=4, down_dims=(16, 32), crop_shape=cfg.crop_shape,
        input_features=inputs, output_features=cfg.output_features, device="cpu",
        pretrained_backbone_weights=None, use_group_norm=True,
    )  # fmt: skip
    dp_chunk = DiffusionPolicy(dp_cfg).eval().predict_action_chunk(batch)  # the same batch suits DP
    assert dp_chunk.shape == chunk.shape


def test_offline_chunk_names_a_batch_without_the_time_axis():
    cfg = tiny_config(n_obs_steps=2)
    with pytest.raises(
        ValueError, match=r"`observation\.state` has shape \(3, 2\), expected \(batch, 2, 2\)"
    ):
        SDPPolicy(cfg).eval().predict_action_chunk(observation(cfg, batch_size=3))


def rollout(policy, cfg, seed, global_seed, n_steps=12):
    """Actions over several chunks drawn with one generator seeded `seed`; the global RNG is reseeded
    from `global_seed` before every step, so a draw that ignores the generator shows up as a
    difference between two rollouts with different `global_seed`."""
    policy.reset()
    gen = torch.Generator().manual_seed(seed)
    actions = []
    for i in range(n_steps):
        torch.manual_seed(1000 * global_seed + i)
        actions.append(policy.select_action(observation(cfg, seed=i), generator=gen))
    return torch.stack(actions)


@pytest.mark.parametrize(
    "overrides",
    [
        dict(action_primer="zero"),  # DDPM: step noise, re-noised past slots, the new tail
        dict(action_primer="constant", n_obs_steps=3),
        dict(action_primer="denoise", noise_scheduler_type="DDIM"),
    ],
)
def test_one_generator_reproduces_the_whole_stream(overrides):
    cfg = tiny_config(**overrides)
    policy = SDPPolicy(cfg, dataset_stats=PUSHT_STATS).eval()
    first = rollout(policy, cfg, seed=7, global_seed=0)
    torch.testing.assert_close(rollout(policy, cfg, seed=7, global_seed=1), first, atol=0, rtol=0)
    assert not torch.allclose(first, rollout(policy, cfg, seed=8, global_seed=0))
    # a second policy with the same weights follows the same stream
    twin = SDPPolicy(cfg, dataset_stats=PUSHT_STATS).eval()
    twin.load_state_dict(policy.state_dict())
    torch.testing.assert_close(rollout(twin, cfg, seed=7, global_seed=2), first, atol=0, rtol=0)


@pytest.mark.parametrize("method", ["select_action", "predict_action_chunk"])
def test_unknown_keywords_are_errors_that_name_them(method):
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    obs = observation(cfg) if method == "select_action" else history(cfg)
    with pytest.raises(TypeError, match=r"\['temperature'\]"):
        getattr(policy, method)(obs, temperature=0.5)
    with pytest.raises(TypeError, match=r"\['noise'\].*generator="):
        getattr(policy, method)(obs, noise=torch.zeros(2, cfg.horizon, 2))


# --- bad input -------------------------------------------------------------------------------


def test_missing_observation_feature_is_named():
    cfg = tiny_config()
    obs = observation(cfg)
    del obs["observation.environment_state"]
    with pytest.raises(ValueError, match=r"missing `observation\.environment_state`"):
        SDPPolicy(cfg).eval().select_action(obs)


def test_misshaped_observation_is_named():
    cfg = tiny_config()
    obs = observation(cfg)
    obs["observation.state"] = torch.rand(2, 3)
    with pytest.raises(ValueError, match=r"`observation.state` has shape \(2, 3\), expected \(batch, 2\)"):
        SDPPolicy(cfg).eval().select_action(obs)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_observation_is_refused(bad):
    cfg = tiny_config()
    obs = observation(cfg)
    obs["observation.environment_state"][0, 3] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        SDPPolicy(cfg).eval().select_action(obs)


def test_constant_primer_needs_state_and_action_in_one_space():
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = tiny_config(action_primer="constant")
    cfg.input_features["observation.state"] = PolicyFeature(FeatureType.STATE, (7,))
    with pytest.raises(ValueError, match=r"not one space.*action_primer=zero"):
        SDPPolicy(cfg)


def test_constant_primer_without_stats_is_a_clear_error():
    cfg = tiny_config(action_primer="constant")
    with pytest.raises(ValueError, match="dataset statistics"):
        SDPPolicy(cfg).eval().select_action(observation(cfg))


def test_constant_primer_starts_from_the_current_state():
    """Normalised state -> raw -> normalised action: the primer is the state in action space."""
    cfg = tiny_config(action_primer="constant")
    policy = SDPPolicy(cfg, dataset_stats=PUSHT_STATS)
    raw = torch.tensor([[100.0, 300.0]])
    s_min, s_max = (
        torch.tensor(PUSHT_STATS["observation.state"]["min"]),
        torch.tensor(PUSHT_STATS["observation.state"]["max"]),
    )
    a_min, a_max = torch.tensor(PUSHT_STATS["action"]["min"]), torch.tensor(PUSHT_STATS["action"]["max"])
    norm_state = (raw - s_min) / (s_max - s_min) * 2 - 1
    batch = {"observation.state": norm_state.unsqueeze(1)}
    primer = policy.model.primer(batch, policy.state_to_action, None)
    torch.testing.assert_close(primer[0, 0], ((raw - a_min) / (a_max - a_min) * 2 - 1)[0])


def test_checkpoint_that_does_not_match_its_config_is_refused(tmp_path):
    SDPPolicy(tiny_config()).save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    config["n_action_steps"] = 8  # a longer horizon: the step encoder no longer fits
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="do not match their SDP config"):
        SDPPolicy.from_pretrained(tmp_path)


def test_wrong_action_horizon_in_batch_is_named():
    cfg = tiny_config()
    batch = training_batch(cfg)
    batch["action"] = batch["action"][:, :5]
    with pytest.raises(ValueError, match="action frames but SDP's horizon"):
        SDPPolicy(cfg).forward(batch)


@pytest.mark.parametrize("separate", [False, True])
def test_two_cameras_condition_the_policy(separate):
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = tiny_config(image=True, crop_shape=(28, 28), use_separate_rgb_encoder_per_camera=separate)
    cfg.input_features["observation.images.wrist"] = PolicyFeature(FeatureType.VISUAL, (3, 32, 32))
    policy = SDPPolicy(cfg)
    loss, _ = policy.forward(training_batch(cfg))
    loss.backward()
    action = policy.eval().select_action(observation(cfg, batch_size=3))
    assert torch.isfinite(loss) and action.shape == (3, 2)


def test_select_action_takes_lerobot_evals_batch():
    """lerobot-eval's observation batch carries `action: None` and the task strings: neither may reach
    the action queue (a queued None broke every evaluation)."""
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    for _ in range(cfg.n_action_steps + 1):
        obs = {**observation(cfg), "action": None, "task": ["push the T", "push the T"]}
        action = policy.select_action(obs)
        assert isinstance(action, torch.Tensor) and action.shape == (2, 2)


def test_drop_queued_actions_drops_the_buffer_and_keeps_the_history():
    """LeRobot's main branch drops queued actions on a conditioning change; SDP's buffer is queued
    future too, so it goes with them, and the next call re-primes from the kept history."""
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    for i in range(2):
        policy.select_action(observation(cfg, seed=i))
    history = list(policy._queues["observation.state"])
    policy.drop_queued_actions()
    assert not policy._queues["action"] and policy._buffer.sample is None
    assert list(policy._queues["observation.state"]) == history
    calls = []
    policy.ema_model.unet.register_forward_hook(lambda *_: calls.append(1))
    assert policy.select_action(observation(cfg, seed=5)).shape == (2, 2)
    assert len(calls) == policy.geometry.steps_per_call and policy._buffer.sample is not None


def test_delay_training_feeds_committed_slots_clean_and_leaves_them_out_of_the_loss(monkeypatch):
    """x0 prediction of the truth everywhere but garbage on the committed slots: loss exactly 0."""
    import lerobot_sdp.modeling_sdp as modeling

    cfg = tiny_config(prediction_type="sample", max_delay=2)
    policy = SDPPolicy(cfg)
    g = policy.geometry
    delays = torch.tensor([0, 1, 2, 2])
    monkeypatch.setattr(
        modeling,
        "sample_delays",
        lambda levels, geometry, generator=None: (
            geometry.delayed(levels, delays, clean=-1),
            geometry.committed_mask(delays),
        ),
    )
    batch = training_batch(cfg)
    seen = {}

    def unet(x, t, global_cond=None):
        seen["x"], seen["t"] = x, t
        return torch.where(g.committed_mask(delays).unsqueeze(-1), 1e3, batch["action"])

    policy.model.unet.forward = unet
    loss, _ = policy.forward(batch)
    assert loss.item() == 0.0
    committed = g.committed_mask(delays)
    assert torch.equal(seen["x"][committed], batch["action"][committed])  # clean inputs, exactly
    assert (seen["t"][committed] == -1).all() and (seen["t"][~committed] >= 0).all()
    assert not torch.equal(seen["x"][~committed], batch["action"][~committed])  # the rest is noised


def test_delay_ready_policy_at_zero_delay_is_the_plain_stream():
    """max_delay = 1 fits tiny_config's padding: same network, and at committed=0 the same actions."""
    torch.manual_seed(0)
    plain = SDPPolicy(tiny_config()).eval()
    ready = SDPPolicy(tiny_config(max_delay=1)).eval()
    assert ready.geometry.horizon == plain.geometry.horizon
    ready.load_state_dict(plain.state_dict())
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    for step in range(3 * plain.config.n_action_steps):
        obs = observation(plain.config, seed=step)
        assert torch.equal(plain.select_action(obs, generator=g1), ready.select_action(obs, generator=g2))
    hist = history(plain.config)
    torch.testing.assert_close(
        plain.predict_action_chunk(hist, generator=g1),
        ready.predict_action_chunk(hist, generator=g2, committed=0),
    )


def test_committed_actions_need_a_policy_trained_for_them():
    policy = SDPPolicy(tiny_config()).eval()
    policy.predict_action_chunk(history(policy.config))
    with pytest.raises(ValueError, match=r"max_delay=0.*--policy\.max_delay"):
        policy.predict_action_chunk(history(policy.config), committed=1)


def test_reset_while_a_chunk_is_computed_leaves_a_fresh_stream():
    torch.manual_seed(0)
    policy = SDPPolicy(tiny_config()).eval()
    reference = SDPPolicy(tiny_config()).eval()
    reference.load_state_dict(policy.state_dict())
    hist = history(policy.config)
    policy.predict_action_chunk(hist)
    hook = policy.ema_model.unet.register_forward_hook(lambda *_: policy.reset())  # the control thread
    with pytest.raises(StreamResetError, match="belongs to the episode that ended"):
        policy.predict_action_chunk(hist)  # its chunk is dropped, never handed to the next episode
    hook.remove()
    assert policy._buffer.sample is None
    torch.testing.assert_close(
        policy.predict_action_chunk(hist, generator=torch.Generator().manual_seed(7)),
        reference.predict_action_chunk(hist, generator=torch.Generator().manual_seed(7)),
    )


def test_dps_generate_actions_samples_the_first_executed_chunk():
    """LeRobot's `DiffusionModel.generate_actions` (inherited) passes its initial sample as `noise`: a
    full denoise from that sample, the executed chunk cut from it; a wrong shape is named."""
    torch.manual_seed(0)
    cfg = tiny_config(noise_scheduler_type="DDIM")
    model = SDPPolicy(cfg).eval().model
    batch = history(cfg, batch_size=3)
    noise = torch.randn(3, cfg.horizon, 2)
    with torch.no_grad():
        actions = model.generate_actions(batch, noise=noise)
        full = model.conditional_sample(3, model.global_conditioning(batch), noise=noise)
    assert actions.shape == (3, cfg.n_action_steps, 2)
    assert torch.equal(actions, full[:, cfg.geometry.executed])
    with pytest.raises(ValueError, match=r"noise has shape \(3, 5, 2\); SDP's initial sample is"):
        model.generate_actions(batch, noise=torch.randn(3, 5, 2))
