"""Timing `select_action` of an SDP policy and the matching LeRobot `DiffusionPolicy`.

How it is measured. Both policies get their own stream of random observations and run `select_action`
on it, one chunk cycle (n_action_steps calls: one that runs the sampler, then queue pops) at a time,
SDP and DP alternating (the machine may be shared: both see the same interference). Warm-up cycles
are run and discarded; then, after a reset, the first call of the stream (SDP's buffer primer) is
reported apart from the steady-state cycles. Forward hooks on the U-Nets and the image encoders count
the denoiser calls and time them (CUDA events on a GPU, so the probes add no synchronisation); the
wall clock synchronises CUDA before every reading. "Bookkeeping" is a sampling call's wall time minus
its denoiser and image-encoder time: queues, buffer, sampler updates, concatenating the conditioning.
"""

import argparse
import itertools
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionPolicy
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.random_utils import set_seed
from torch import nn
from tqdm import tqdm

from ..chunk_cost import CallProbe
from ..configuration_sdp import SDPConfig
from ..modeling_sdp import SDPPolicy
from .matched_dp import matching_dp_config

# State-based Push-T (agent position 2, T-block keypoints 16) and image Push-T (one 96 x 96 camera,
# the agent position as state); the action is the 2-D target position.
OBSERVATIONS = {
    "state": {
        "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (16,)),
    },
    "image": {
        "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
        "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 96, 96)),
    },
}

ACTION_FEATURE = {"action": PolicyFeature(FeatureType.ACTION, (2,))}

# The paper's U-Nets for state and image Push-T, and a tiny one for --quick.
UNET_PRESETS = {
    "state": {"down_dims": [256, 512, 1024], "diffusion_step_embed_dim": 256},
    "image": {"down_dims": [512, 1024, 2048], "diffusion_step_embed_dim": 128},
    "quick": {"down_dims": [32, 64, 128], "diffusion_step_embed_dim": 32},
}

OBSERVATION_POOL = 4  # distinct observations each stream cycles through


@dataclass(frozen=True)
class Sampler:
    """A noise scheduler and its number of inference steps N, written e.g. DDIM16."""

    scheduler: str
    steps: int

    @classmethod
    def parse(cls, text: str) -> "Sampler":
        match = re.fullmatch(r"(DDPM|DDIM)(\d+)", text.upper())
        if match is None or int(match[2]) <= 0:
            raise argparse.ArgumentTypeError(f"sampler must look like DDPM100 or DDIM16, got {text!r}")
        return cls(match[1], int(match[2]))

    def __str__(self) -> str:
        return f"{self.scheduler}{self.steps}"


@dataclass(frozen=True)
class Case:
    """One measured configuration: an SDP policy and its matching DP, timed side by side."""

    device: str
    batch_size: int
    sampler: Sampler
    n_chunks: int

    def describe(self) -> dict:
        return {
            "device": self.device,
            "batch_size": self.batch_size,
            "sampler": str(self.sampler),
            "noise_scheduler_type": self.sampler.scheduler,
            "num_inference_steps": self.sampler.steps,
            "n_chunks": self.n_chunks,
        }

    def skip_reason(self) -> str | None:
        # SDPConfig refuses these too (chunk levels would drift); the sweep records them instead.
        if self.sampler.steps % self.n_chunks:
            return f"N={self.sampler.steps} is not divisible by h={self.n_chunks} (SDP needs N % h == 0)"
        return None


def sdp_config(args: argparse.Namespace, case: Case) -> SDPConfig:
    return SDPConfig(
        n_obs_steps=args.n_obs_steps,
        n_action_steps=args.n_action_steps,
        n_chunks=case.n_chunks,
        down_dims=tuple(args.down_dims),
        diffusion_step_embed_dim=args.diffusion_step_embed_dim,
        kernel_size=args.kernel_size,
        noise_scheduler_type=case.sampler.scheduler,
        num_inference_steps=case.sampler.steps,
        crop_shape=(84, 84),  # LeRobot's Push-T DP crop of the 96 px camera (centre crop in eval)
        use_group_norm=True,
        pretrained_backbone_weights=None,
        action_primer=args.action_primer,
        compile_model=args.compile,
        device=case.device,
        input_features=OBSERVATIONS[args.obs],
        output_features=ACTION_FEATURE,
    )


def build_policies(args: argparse.Namespace, case: Case) -> tuple[SDPPolicy, DiffusionPolicy]:
    sdp_cfg = sdp_config(args, case)
    dp_cfg = matching_dp_config(sdp_cfg)
    set_seed(args.seed)
    sdp = SDPPolicy(sdp_cfg).to(case.device).eval()
    set_seed(args.seed)
    dp = DiffusionPolicy(dp_cfg).to(case.device).eval()
    return sdp, dp


def expected_denoiser_calls(policy: PreTrainedPolicy) -> int:
    """What theory says a steady-state chunk costs (N/h for SDP, N for DP), printed beside the count."""
    if isinstance(policy, SDPPolicy):
        return policy.geometry.steps_per_call
    return policy.diffusion.num_inference_steps


def image_encoders(policy: nn.Module) -> list[nn.Module]:
    """The camera encoders (none for state observations: their "encoder" is a concatenation). One
    encoder per camera sits in a ModuleList, which is never called itself: hook its members."""
    encoders = []
    for model in policy.modules():
        if isinstance(model, DiffusionModel) and hasattr(model, "rgb_encoder"):
            encoder = model.rgb_encoder
            encoders.extend(encoder if isinstance(encoder, nn.ModuleList) else [encoder])
    return encoders


class Clock:
    """Wall clock that first waits for the device, so a reading includes all queued GPU work."""

    def __init__(self, device: torch.device):
        self.device = device

    def now(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()


def observation_stream(
    features: dict[str, PolicyFeature], batch_size: int, device: str, generator: torch.Generator
) -> Iterator[dict[str, torch.Tensor]]:
    """Endless stream of random (normalised-scale) observations, made before timing starts."""

    def observation() -> dict[str, torch.Tensor]:
        return {
            key: torch.randn((batch_size, *ft.shape), generator=generator).to(device)
            for key, ft in features.items()
        }

    pool = [observation() for _ in range(OBSERVATION_POOL)]
    return itertools.cycle(pool)


@dataclass
class Cycle:
    """One chunk cycle: the select_action call that ran the sampler, then the queue pops."""

    chunk_s: float  # the sampling call
    cycle_s: float  # all n_action_steps calls, the sampling call included
    denoiser_calls: int
    denoiser_s: float
    encoder_s: float

    @property
    def bookkeeping_s(self) -> float:
        return self.chunk_s - self.denoiser_s - self.encoder_s


@dataclass
class Contender:
    """A policy under test with its observation stream and probes."""

    name: str
    policy: PreTrainedPolicy
    observations: Iterator[dict[str, torch.Tensor]]
    denoiser: CallProbe
    encoder: CallProbe

    def run_cycle(self, chunk_len: int, clock: Clock) -> Cycle:
        self.denoiser.reset()
        self.encoder.reset()
        start = clock.now()
        self.policy.select_action(next(self.observations))
        sampled = clock.now()
        sampling_calls = self.denoiser.calls
        for _ in range(chunk_len - 1):
            self.policy.select_action(next(self.observations))
        end = clock.now()
        if self.denoiser.calls != sampling_calls or sampling_calls == 0:
            raise RuntimeError(
                f"{self.name}: the denoiser ran {sampling_calls} times in the first call of a chunk cycle "
                "and "
                f"{self.denoiser.calls - sampling_calls} times in the queue pops: the cycles are misaligned."
            )
        return Cycle(
            chunk_s=sampled - start,
            cycle_s=end - start,
            denoiser_calls=sampling_calls,
            denoiser_s=self.denoiser.seconds(),
            encoder_s=self.encoder.seconds(),
        )


def measure(
    contenders: list[Contender], args: argparse.Namespace, clock: Clock, progress: tqdm
) -> tuple[dict[str, Cycle], dict[str, list[Cycle]]]:
    """Warm-up (discarded), then the primer cycle and ``args.steps`` steady cycles per policy, the
    policies alternating cycle by cycle (and which goes first alternating too). Returns the primer
    and the steady cycles per policy name; steady cycle i of both policies ran back to back."""

    def cycle(contender: Contender) -> Cycle:
        result = contender.run_cycle(args.n_action_steps, clock)
        progress.update()
        return result

    for contender in contenders:
        contender.policy.reset()
        for _ in range(args.warmup_chunks):
            cycle(contender)
    for contender in contenders:
        contender.policy.reset()
    primers = {c.name: cycle(c) for c in contenders}
    steady: dict[str, list[Cycle]] = {c.name: [] for c in contenders}
    for step in range(args.steps):
        for contender in contenders if step % 2 else contenders[::-1]:
            steady[contender.name].append(cycle(contender))
    return primers, steady


@contextmanager
def cpu_threads(n: int | None) -> Iterator[None]:
    """Use ``n`` torch CPU threads inside the block (``None``: leave torch's choice), then restore
    the previous number, so an in-process caller (a test) keeps its own setting."""
    previous = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
