"""The LeRobot Diffusion Policy that an SDP config is compared with, defined once.

Every comparison in the benchmarks (latency, train-step profile, quality at equal budget) gives DP
every field that `SDPConfig` and LeRobot's `DiffusionConfig` share (observation and action steps,
U-Net, noise scheduler, optimiser and learning-rate schedule, ...) with SDP's value, so that the
two differ only where the algorithms do, and a horizon: SDP's own (the same denoiser input) unless
a benchmark asks for another (LeRobot's Push-T reference uses 16).

`DiffusionConfig` asks for a horizon divisible by 2**len(down_dims), stricter than its U-Net needs
(it downsamples len(down_dims) - 1 times, the multiple SDP's geometry pads to): a config is built at
the next such multiple and its horizon set back afterwards, so DP never gets a longer (slower)
sequence than SDP.
"""

import copy
from dataclasses import fields

from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from ..configuration_sdp import SDPConfig
from ..geometry import round_up

# Not a modelling choice: LeRobot's DP default downloads ImageNet weights, SDP's default is none.
DP_ONLY = {"pretrained_backbone_weights": None}


def shared_fields() -> set[str]:
    """The fields DP takes over from SDP: those both configs have."""
    return {f.name for f in fields(SDPConfig)} & {f.name for f in fields(DiffusionConfig) if f.init}


def matching_dp_config(sdp: SDPConfig, horizon: int | None = None) -> DiffusionConfig:
    """LeRobot's DiffusionConfig with every shared field copied from ``sdp`` and ``horizon``
    (default: SDP's)."""
    values = {name: copy.deepcopy(getattr(sdp, name)) for name in shared_fields()}
    horizon = horizon or sdp.horizon
    config = DiffusionConfig(**values, horizon=round_up(horizon, 2 ** len(sdp.down_dims)))
    config.horizon = horizon  # after DiffusionConfig's validation (module docstring)
    return config


def matching_dp_flags(sdp_flags: list[str], horizon: int) -> list[str]:
    """`lerobot-train` flags for the DP matching an SDP given by ``sdp_flags`` (`--policy.X=v`): the
    flags of shared fields, the type, ``horizon`` and no pretrained backbone download."""
    shared = shared_fields()
    kept = [f for f in sdp_flags if f.startswith("--policy.") and f[9:].split("=")[0].split(".")[0] in shared]
    extra = [f"--policy.{k}={'null' if v is None else v}" for k, v in DP_ONLY.items()]
    return ["--policy.type=diffusion", *kept, f"--policy.horizon={horizon}", *extra]
