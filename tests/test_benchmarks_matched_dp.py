"""The DP every benchmark compares SDP with (`benchmarks/matched_dp.py`): every field the two
configs share taken from SDP, SDP's horizon unless asked otherwise, the same rule for config
objects and for `lerobot-train` flags."""

from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from lerobot_sdp.benchmarks.matched_dp import matching_dp_config, matching_dp_flags, shared_fields
from lerobot_sdp.configuration_sdp import SDPConfig


def non_default_sdp() -> SDPConfig:
    return SDPConfig(
        n_obs_steps=3,
        n_action_steps=6,
        down_dims=(32, 64),
        kernel_size=3,
        diffusion_step_embed_dim=48,
        noise_scheduler_type="DDIM",
        num_inference_steps=8,
        optimizer_lr=3e-4,
        scheduler_warmup_steps=123,
        beta_schedule="linear",
    )


def test_dp_takes_every_shared_field_and_sdps_horizon():
    sdp = non_default_sdp()
    dp = matching_dp_config(sdp)
    assert isinstance(dp, DiffusionConfig)
    assert {"down_dims", "optimizer_lr", "n_obs_steps", "beta_schedule"} <= shared_fields()
    assert not {"n_chunks", "max_delay", "use_ema", "noise_schemes"} & shared_fields()
    for name in shared_fields():
        assert getattr(dp, name) == getattr(sdp, name), name
    assert sdp.horizon % 4 != 0 and dp.horizon == sdp.horizon  # not DiffusionConfig's multiple of 4
    assert matching_dp_config(sdp, horizon=16).horizon == 16


def test_flags_keep_the_shared_fields_only():
    sdp_flags = [
        "--policy.type=sdp",
        "--policy.down_dims=[32,64]",
        "--policy.optimizer_lr=0.0003",
        "--policy.n_chunks=4",
        "--policy.noise_schemes.independent=0.5",
        "--policy.use_ema=false",
        "--steps=10",
    ]
    assert matching_dp_flags(sdp_flags, 24) == [
        "--policy.type=diffusion",
        "--policy.down_dims=[32,64]",
        "--policy.optimizer_lr=0.0003",
        "--policy.horizon=24",
        "--policy.pretrained_backbone_weights=null",
    ]
