"""SDPConfig: derived geometry, LeRobot's delta indices, CLI parsing and clear errors."""

import logging

import draccus
import pytest
from sdp_test_utils import tiny_config

from lerobot_sdp import SDPConfig
from lerobot_sdp.noise_schemes import NoiseSchemeWeights


def test_horizon_is_derived_and_reported(caplog):
    with caplog.at_level(logging.INFO):
        cfg = SDPConfig(n_obs_steps=2, n_action_steps=8, n_chunks=2, down_dims=(256, 512, 1024))
    assert cfg.horizon == 20
    assert "horizon=20 (1 past + 2 chunks x 8 + 3 padding), 50 denoiser calls per chunk" in caplog.text


def test_delta_indices_cover_past_and_all_chunks():
    cfg = tiny_config(n_obs_steps=2, n_action_steps=4, n_chunks=2)  # U-Net factor 2: horizon 10
    assert cfg.observation_delta_indices == [-1, 0]
    assert cfg.action_delta_indices == list(range(-1, 9))
    assert cfg.drop_n_last_frames == 3  # the executed chunk of 4 ends on the last frame
    assert cfg.reward_delta_indices is None


def test_offline_safe_defaults():
    cfg = SDPConfig()
    assert cfg.pretrained_backbone_weights is None and cfg.use_group_norm and cfg.push_to_hub is False
    assert cfg.noise_schemes == NoiseSchemeWeights(constant=0.2, linear=0.0, independent=0.0, chunkwise=0.8)
    assert cfg.action_primer == "zero" and cfg.type == "sdp"


def test_noise_scheme_weights_parse_from_the_command_line():
    cfg = draccus.parse(
        SDPConfig,
        args=[
            "--noise_schemes.independent=0.67",
            "--noise_schemes.linear=0.33",
            "--noise_schemes.chunkwise=0",
            "--noise_schemes.constant=0",
        ],
    )
    assert cfg.noise_schemes.as_dict() == {
        "constant": 0.0,
        "linear": 0.33,
        "independent": 0.67,
        "chunkwise": 0.0,
        "independent_chunks": 0.0,
    }


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (
            dict(n_chunks=3),
            r"num_inference_steps=100 is not divisible by n_chunks=3.*Change `num_inference_steps`",
        ),
        (dict(n_action_steps=0), "`n_action_steps` must be positive"),
        (dict(num_inference_steps=200), "num_inference_steps=200 > num_train_timesteps=100"),
        (dict(action_primer="ones"), "`action_primer` must be one of"),
        (dict(prediction_type="v"), "`prediction_type` must be one of"),
        (dict(noise_scheduler_type="DPM"), "`noise_scheduler_type` must be one of"),
        (dict(down_dims=()), "`down_dims`"),
    ],
)
def test_impossible_configs_fail_at_build_time_naming_the_value(kwargs, match, caplog):
    with pytest.raises(ValueError, match=match):
        SDPConfig(**kwargs)
    assert "Invalid SDP config" in caplog.text  # logged too: draccus hides the exception's text


def test_features_are_validated():
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = tiny_config()
    cfg.input_features.pop("observation.environment_state")
    with pytest.raises(ValueError, match="at least one camera"):
        cfg.validate_features()
    cfg = tiny_config(image=True, crop_shape=(40, 40))
    with pytest.raises(ValueError, match=r"does not fit `observation\.image`"):
        cfg.validate_features()
    cfg = tiny_config()
    cfg.input_features.pop("observation.state")
    with pytest.raises(ValueError, match=r"needs `observation\.state`"):
        cfg.validate_features()
    cfg = tiny_config(image=True)
    cfg.input_features["observation.image2"] = PolicyFeature(FeatureType.VISUAL, (3, 64, 64))
    with pytest.raises(ValueError, match="share one shape"):
        cfg.validate_features()


def test_the_optimizer_preset_is_lerobots_adam_with_torchs_fused_kernel():
    import draccus
    import torch
    from lerobot.optim import AdamConfig, OptimizerConfig

    params = [torch.nn.Parameter(torch.ones(3))]
    preset = tiny_config(optimizer_lr=0.003).get_optimizer_preset()
    optimizer = preset.build(params)
    assert type(optimizer) is torch.optim.Adam
    assert optimizer.defaults["fused"] is True and optimizer.defaults["lr"] == 0.003
    # saved in train_config.json under its own type name, and read back as itself (resume)
    encoded = draccus.encode(preset, OptimizerConfig)
    assert encoded["type"] == "adam_fused"
    assert draccus.decode(OptimizerConfig, encoded) == preset
    plain = tiny_config(optimizer_fused=False).get_optimizer_preset()
    assert type(plain) is AdamConfig and not plain.build(params).defaults["fused"]


def test_the_fused_adam_takes_the_same_steps_as_lerobots():
    import torch

    torch.manual_seed(0)
    weights = [torch.randn(5, 4), torch.randn(7)]
    runs = []
    for fused in (True, False):
        params = [torch.nn.Parameter(w.clone()) for w in weights]
        optimizer = tiny_config(optimizer_fused=fused, optimizer_lr=0.01).get_optimizer_preset().build(params)
        for step in range(5):
            for p in params:
                p.grad = torch.sin(p.detach() * (step + 1))
            optimizer.step()
        runs.append(params)
    for fused, plain, start in zip(*runs, weights, strict=True):
        assert (fused.detach() - start).abs().min() > 1e-3  # every weight moved
        torch.testing.assert_close(fused, plain, rtol=1e-6, atol=1e-6)
