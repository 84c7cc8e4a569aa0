"""Latency of `select_action`: SDP against LeRobot's Diffusion Policy, same denoiser, same N.

What is compared. For every (device, batch size, sampler, h) case one SDP policy and one LeRobot
`DiffusionPolicy` are built from one set of fields: the DP config copies every field the two configs
share (U-Net size, observation encoder, scheduler, N, n_obs_steps, n_action_steps, compile...), and
DP's horizon is set to SDP's horizon for that h, so both denoise the same (B, horizon, A) sequence
with the same U-Net. That is the paper's "prediction time vs horizon" comparison: DP's cost per chunk
moves with h only through the horizon length, SDP's divides by h. The one architectural difference
left is SDP's per-slot step encoder (sdp-algorithm.md, section 5), and it is part of what is timed.
Weights are random (untrained): latency does not depend on their values.

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
import copy
import importlib.metadata
import itertools
import json
import logging
import os
import platform
import re
import time
from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Self

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionPolicy
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.random_utils import set_seed
from matplotlib.figure import Figure
from torch import nn
from tqdm import tqdm

from ..configuration_sdp import SDPConfig
from ..modeling_sdp import SDPPolicy

logger = logging.getLogger(__name__)

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
TARGET_RATIO = 1.1  # issue 4: SDP / DP time per chunk <= 1.1 / h
OBSERVATION_POOL = 4  # distinct observations each stream cycles through
JSON_NAME = "latency.json"
PLOT_NAME = "latency_h_sweep.png"


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


# What a full run and a --quick (CI-sized) run measure unless a flag says otherwise.
RUN_PRESETS = {
    "full": {
        "batch_sizes": [1, 64],
        "samplers": [Sampler("DDPM", 100), Sampler("DDIM", 10), Sampler("DDIM", 16)],
        "n_chunks": [1, 2, 4, 8],
        "steps": 20,
    },
    "quick": {"batch_sizes": [1], "samplers": [Sampler("DDIM", 10)], "n_chunks": [1, 2], "steps": 3},
}


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


# ---------------------------------------------------------------------------------------------------
# The two policies


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


def matching_dp_config(sdp: SDPConfig) -> DiffusionConfig:
    """LeRobot's DiffusionConfig with every field the two configs share copied from ``sdp``, and the
    same horizon."""
    shared = {f.name for f in fields(SDPConfig)} & {f.name for f in fields(DiffusionConfig) if f.init}
    values = {name: copy.deepcopy(getattr(sdp, name)) for name in shared}
    factor = 2 ** len(sdp.down_dims)
    config = DiffusionConfig(**values, horizon=-(-sdp.horizon // factor) * factor)
    # DiffusionConfig checks divisibility by 2**len(down_dims), but its U-Net only downsamples
    # len(down_dims) - 1 times, which is what SDP's geometry pads to: set the exact same length
    # after validation, so DP does not get a longer (slower) sequence than SDP.
    config.horizon = sdp.horizon
    return config


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


def denoisers(policy: nn.Module) -> list[nn.Module]:
    """The U-Nets (EMA copy included), as attributes: a compiled U-Net is hooked on its wrapper."""
    return [m.unet for m in policy.modules() if isinstance(m, DiffusionModel)]


def image_encoders(policy: nn.Module) -> list[nn.Module]:
    """The camera encoders (none for state observations: their "encoder" is a concatenation). One
    encoder per camera sits in a ModuleList, which is never called itself: hook its members."""
    encoders = []
    for model in policy.modules():
        if isinstance(model, DiffusionModel) and hasattr(model, "rgb_encoder"):
            encoder = model.rgb_encoder
            encoders.extend(encoder if isinstance(encoder, nn.ModuleList) else [encoder])
    return encoders


# ---------------------------------------------------------------------------------------------------
# Clocks and probes


class Clock:
    """Wall clock that first waits for the device, so a reading includes all queued GPU work."""

    def __init__(self, device: torch.device):
        self.device = device

    def now(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()


class CallProbe:
    """Counts and times the forward calls of some modules through forward hooks (counted, never
    inferred). On CUDA the intervals are CUDA events, read only after the clock has synchronised, so
    probing adds no synchronisation of its own. Use as a context manager (removes the hooks)."""

    def __init__(self, modules: Iterable[nn.Module], device: torch.device):
        self._cuda = device.type == "cuda"
        self._intervals: list[list] = []
        self._handles = []
        for module in modules:
            self._handles.append(module.register_forward_pre_hook(self._start))
            self._handles.append(module.register_forward_hook(self._stop))

    def _marker(self):
        if not self._cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def _start(self, module, args) -> None:
        self._intervals.append([self._marker(), None])

    def _stop(self, module, args, output) -> None:
        self._intervals[-1][1] = self._marker()

    @property
    def calls(self) -> int:
        return len(self._intervals)

    def seconds(self) -> float:
        if self._cuda:
            return sum(start.elapsed_time(stop) for start, stop in self._intervals) / 1000
        return sum(stop - start for start, stop in self._intervals)

    def reset(self) -> None:
        self._intervals.clear()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        for handle in self._handles:
            handle.remove()


# ---------------------------------------------------------------------------------------------------
# Streams and chunk cycles


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


# ---------------------------------------------------------------------------------------------------
# Statistics


def percentiles_ms(values_s: list[float]) -> dict:
    p50, p95 = np.percentile(np.asarray(values_s) * 1000, [50, 95])
    return {"p50": float(p50), "p95": float(p95), "mean": float(np.mean(values_s) * 1000), "n": len(values_s)}


def percentiles(values: list[float]) -> dict:
    p50, p95 = np.percentile(values, [50, 95])
    return {"p50": float(p50), "p95": float(p95)}


def summarise(policy: PreTrainedPolicy, primer: Cycle, steady: list[Cycle], chunk_len: int) -> dict:
    counts = sorted({c.denoiser_calls for c in steady})
    if len(counts) != 1:
        raise RuntimeError(f"{policy.name}: denoiser calls per chunk varied between chunks: {counts}")
    per_call = [c.denoiser_s / c.denoiser_calls for c in steady]
    return {
        "denoiser_calls_per_chunk": counts[0],
        "expected_denoiser_calls_per_chunk": expected_denoiser_calls(policy),
        "primer": {
            "latency_ms": primer.chunk_s * 1000,
            "denoiser_calls": primer.denoiser_calls,
            "per_action_ms": primer.cycle_s / chunk_len * 1000,
        },
        "chunk_latency_ms": percentiles_ms([c.chunk_s for c in steady]),
        "chunk_latency_samples_ms": [c.chunk_s * 1000 for c in steady],
        "per_action_ms": percentiles_ms([c.cycle_s / chunk_len for c in steady]),
        "denoiser_call_ms": percentiles_ms(per_call),
        "image_encoder_ms": percentiles_ms([c.encoder_s for c in steady]),
        "bookkeeping_ms": percentiles_ms([c.bookkeeping_s for c in steady]),
        "bookkeeping_fraction_of_denoiser_call": percentiles(
            [c.bookkeeping_s / call for c, call in zip(steady, per_call, strict=True)]
        ),
    }


def ratios(case: Case, sdp: dict, dp: dict, paired: list[float]) -> dict:
    """SDP / DP time per chunk (ratio of the p50s) against the target 1.1/h. ``paired`` holds the
    ratios of the chunks that ran back to back: their median is robust to a machine whose load drifts."""
    chunk = sdp["chunk_latency_ms"]["p50"] / dp["chunk_latency_ms"]["p50"]
    target = TARGET_RATIO / case.n_chunks
    return {
        "sdp_over_dp_chunk_p50": chunk,
        "sdp_over_dp_chunk_paired_p50": float(np.median(paired)),
        "sdp_over_dp_per_action_p50": sdp["per_action_ms"]["p50"] / dp["per_action_ms"]["p50"],
        "ideal": 1 / case.n_chunks,
        "target": target,
        "meets_target": chunk <= target,
    }


# ---------------------------------------------------------------------------------------------------
# One case, the sweep, the environment


def run_case(args: argparse.Namespace, case: Case, progress: tqdm) -> dict:
    """Build the SDP / DP pair for ``case``, time them side by side, return the case's JSON entry."""
    sdp, dp = build_policies(args, case)
    device = torch.device(case.device)
    generator = torch.Generator().manual_seed(args.seed)
    features = OBSERVATIONS[args.obs]
    with ExitStack() as hooks:
        contenders = [
            Contender(
                name=name,
                policy=policy,
                observations=observation_stream(features, case.batch_size, case.device, generator),
                denoiser=hooks.enter_context(CallProbe(denoisers(policy), device)),
                encoder=hooks.enter_context(CallProbe(image_encoders(policy), device)),
            )
            for name, policy in (("sdp", sdp), ("dp", dp))
        ]
        primers, steady = measure(contenders, args, Clock(device), progress)
    stats = {
        c.name: summarise(c.policy, primers[c.name], steady[c.name], args.n_action_steps) for c in contenders
    }
    paired = [s.chunk_s / d.chunk_s for s, d in zip(steady["sdp"], steady["dp"], strict=True)]
    return {
        **case.describe(),
        "horizon": sdp.config.horizon,
        **stats,
        "ratio": ratios(case, **stats, paired=paired),
    }


def cases(args: argparse.Namespace) -> list[Case]:
    """Every (device, batch size, sampler, h) combination, in that nesting order."""
    return [
        Case(device, batch, sampler, h)
        for device in args.device
        for batch in args.batch_sizes
        for sampler in args.samplers
        for h in args.n_chunks
    ]


def cpu_model() -> str:
    """The CPU's marketing name (what `lscpu` prints as "Model name")."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(args: argparse.Namespace) -> dict:
    """Library versions and hardware the figures were taken on."""
    env = {
        "python": platform.python_version(),
        **{pkg: importlib.metadata.version(pkg) for pkg in ("torch", "lerobot", "diffusers", "numpy")},
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch_num_threads": torch.get_num_threads(),
        "cuda_available": torch.cuda.is_available(),
    }
    if "cuda" in args.device:
        env["gpu"] = torch.cuda.get_device_name()
    return env


def settings(args: argparse.Namespace) -> dict:
    """Every resolved flag (the run can be repeated from them), and the two choices that matter."""
    return {
        **{key: value for key, value in vars(args).items() if key != "subcommand"},
        "weights": "random (untrained): latency does not depend on the weight values",
        "dp_horizon": "equal to SDP's horizon for the same h (same denoiser input)",
    }


# ---------------------------------------------------------------------------------------------------
# Output


def measured_results(results: list[dict]) -> list[dict]:
    return [r for r in results if "skipped" not in r]


def plot_h_sweep(results: list[dict], path: Path) -> None:
    """One row per (device, batch): time per chunk vs horizon (SDP solid, DP dashed; the paper's
    "prediction time vs horizon" figure), and SDP / DP time per chunk vs h against 1/h and 1.1/h."""
    measured = measured_results(results)
    groups = sorted({(r["device"], r["batch_size"]) for r in measured})
    fig = Figure(figsize=(10, 3.6 * len(groups)), layout="constrained")
    axes = fig.subplots(len(groups), 2, squeeze=False)
    for (device, batch), (ax_time, ax_ratio) in zip(groups, axes, strict=True):
        rows = [r for r in measured if (r["device"], r["batch_size"]) == (device, batch)]
        for index, sampler in enumerate(dict.fromkeys(r["sampler"] for r in rows)):
            line = sorted((r for r in rows if r["sampler"] == sampler), key=lambda r: r["n_chunks"])
            horizon = [r["horizon"] for r in line]
            for policy, style in (("sdp", "o-"), ("dp", "s--")):
                p50 = [r[policy]["chunk_latency_ms"]["p50"] for r in line]
                ax_time.plot(horizon, p50, style, color=f"C{index}", label=f"{policy.upper()} {sampler}")
            ratio = [r["ratio"]["sdp_over_dp_chunk_p50"] for r in line]
            ax_ratio.plot([r["n_chunks"] for r in line], ratio, "o-", color=f"C{index}", label=sampler)
        h = np.array(sorted({r["n_chunks"] for r in rows}), dtype=float)
        ax_ratio.plot(h, 1 / h, ":", color="gray", label="ideal 1/h")
        ax_ratio.plot(h, TARGET_RATIO / h, "-", color="gray", alpha=0.5, label=f"target {TARGET_RATIO}/h")
        title = f"{device}, batch {batch}"
        ax_time.set(yscale="log", xlabel="horizon (slots)", ylabel="time per chunk, p50 [ms]", title=title)
        ax_ratio.set(
            xscale="log", yscale="log", xlabel="chunks in the buffer h", ylabel="SDP / DP", title=title
        )
        # Log-log makes 1/h a straight line; tick the measured h and their 1/h, not powers of ten.
        ax_ratio.set_xticks(h, [f"{v:g}" for v in h])
        ax_ratio.set_yticks(1 / h, [f"{v:.3g}" for v in 1 / h])
        ax_ratio.minorticks_off()
        for ax in (ax_time, ax_ratio):
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize="small")
    fig.savefig(path, dpi=80)


def markdown_table(results: list[dict]) -> str:
    """The summary printed at the end (and pasted into docs/benchmarks.md): one row per measured case."""
    header = (
        "| device | batch | sampler | h | horizon | calls/chunk SDP / DP | SDP chunk p50 / p95 ms "
        "| DP chunk p50 / p95 ms | per action p50 ms SDP / DP | SDP primer ms | SDP/DP (paired) "
        "| target 1.1/h | bookkeeping p50, % of a U-Net call, SDP / DP |"
    )
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in measured_results(results):
        sdp, dp, ratio = r["sdp"], r["dp"], r["ratio"]
        lines.append(
            f"| {r['device']} | {r['batch_size']} | {r['sampler']} | {r['n_chunks']} | {r['horizon']} "
            f"| {sdp['denoiser_calls_per_chunk']} / {dp['denoiser_calls_per_chunk']} "
            f"| {sdp['chunk_latency_ms']['p50']:.1f} / {sdp['chunk_latency_ms']['p95']:.1f} "
            f"| {dp['chunk_latency_ms']['p50']:.1f} / {dp['chunk_latency_ms']['p95']:.1f} "
            f"| {sdp['per_action_ms']['p50']:.2f} / {dp['per_action_ms']['p50']:.2f} "
            f"| {sdp['primer']['latency_ms']:.1f} "
            f"| {ratio['sdp_over_dp_chunk_p50']:.3f} ({ratio['sdp_over_dp_chunk_paired_p50']:.3f}) "
            f"| {ratio['target']:.3f} "
            f"| {100 * sdp['bookkeeping_fraction_of_denoiser_call']['p50']:.1f} "
            f"/ {100 * dp['bookkeeping_fraction_of_denoiser_call']['p50']:.1f} |"
        )
    return "\n".join(lines)


def write_json(report: dict, output_dir: Path) -> None:
    # default=str: paths and samplers are written as their command-line spelling.
    (output_dir / JSON_NAME).write_text(json.dumps(report, indent=2, default=str))


# ---------------------------------------------------------------------------------------------------
# Command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    full = RUN_PRESETS["full"]
    devices = ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    add = parser.add_argument
    add("--output_dir", type=Path, default=Path("outputs/benchmarks/latency"))
    add("--overwrite", action="store_true", help=f"replace an existing {JSON_NAME} in --output_dir")
    add(
        "--obs",
        choices=sorted(OBSERVATIONS),
        default="state",
        help="state: Push-T state features; image: one 96x96 camera (GroupNorm ResNet18, random weights)",
    )
    add("--quick", action="store_true", help="CI-sized run: tiny U-Net, one sampler, h 1 2, 3 chunks")
    add("--device", nargs="+", default=devices, help=f"default: {' '.join(devices)}")
    add("--batch_sizes", nargs="+", type=int, help=f"default: {full['batch_sizes']}")
    add(
        "--samplers",
        nargs="+",
        type=Sampler.parse,
        help=f"scheduler and N (inference steps), default: {' '.join(map(str, full['samplers']))}",
    )
    add("--n_chunks", nargs="+", type=int, help=f"values of h to sweep, default: {full['n_chunks']}")
    add("--steps", type=int, help=f"steady chunks measured per policy and case, default: {full['steps']}")
    add("--warmup_chunks", type=int, default=1, help="chunk cycles run and discarded per policy and case")
    add("--n_obs_steps", type=int, default=2)
    add("--n_action_steps", type=int, default=8, help="chunk length Tb, fixed across the h sweep")
    add("--down_dims", nargs="+", type=int, help="U-Net widths, default: the paper's U-Net for --obs")
    add("--diffusion_step_embed_dim", type=int, help="default: the paper's value for --obs")
    add("--kernel_size", type=int, default=5)
    add(
        "--action_primer",
        choices=["zero", "denoise"],
        default="zero",
        help="SDP's buffer initialisation ('constant' costs what 'zero' costs but needs dataset statistics)",
    )
    add("--compile", action="store_true", help="torch.compile the U-Net of both policies")
    add("--num_threads", type=int, help="torch CPU threads (default: torch's choice)")
    add("--seed", type=int, default=0)


def resolve_defaults(args: argparse.Namespace) -> None:
    """Fill the flags left unset from the full or --quick preset (an explicit flag always wins)."""
    run_preset = RUN_PRESETS["quick" if args.quick else "full"]
    unet_preset = UNET_PRESETS["quick" if args.quick else args.obs]
    for name, value in {**run_preset, **unet_preset}.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.steps < 1 or args.warmup_chunks < 0 or min(args.n_chunks) < 1 or min(args.batch_sizes) < 1:
        raise SystemExit("--steps, --n_chunks and --batch_sizes must be >= 1 and --warmup_chunks >= 0.")
    if "cuda" in args.device and not torch.cuda.is_available():
        raise SystemExit("--device cuda was asked for but no CUDA GPU is available.")


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


def run(args: argparse.Namespace) -> dict:
    """Run the sweep, write latency.json and latency_h_sweep.png under --output_dir, print a table."""
    resolve_defaults(args)
    if (args.output_dir / JSON_NAME).exists() and not args.overwrite:
        raise SystemExit(
            f"{args.output_dir / JSON_NAME} exists: pass --overwrite to replace it, or another --output_dir."
        )
    args.output_dir.mkdir(parents=True, exist_ok=True)
    with cpu_threads(args.num_threads):
        report = {
            "benchmark": "latency",
            "environment": environment(args),
            "settings": settings(args),
            "results": [],
        }
        todo = cases(args)
        measured = [c for c in todo if c.skip_reason() is None]
        per_case = 2 * (args.warmup_chunks + 1 + args.steps)
        with tqdm(total=per_case * len(measured), unit="chunk", desc="latency") as progress:
            for case in todo:
                reason = case.skip_reason()
                if reason:
                    logger.info("Skipping %s: %s", case.describe(), reason)
                    report["results"].append({**case.describe(), "skipped": reason})
                    continue
                progress.set_postfix_str(
                    f"{case.device} b={case.batch_size} {case.sampler} h={case.n_chunks}"
                )
                report["results"].append(run_case(args, case, progress))
                write_json(report, args.output_dir)  # keep what is done if a long run is interrupted
    write_json(report, args.output_dir)
    if measured_results(report["results"]):
        plot_h_sweep(report["results"], args.output_dir / PLOT_NAME)
        print(markdown_table(report["results"]))
    logger.info("Wrote %s", args.output_dir / JSON_NAME)
    return report
