"""Eager against compiled: time per chunk of SDP and LeRobot's Diffusion Policy, and per denoiser call
against the memory-bandwidth floor.

For every batch size, four policies with the same weights per family run side by side: SDP eager, SDP
with `compile_model` (its whole streaming step compiled as one graph; a CUDA graph on a GPU), DP eager
and DP with LeRobot's `compile_model` (its U-Net compiled). Compilation happens in the warm-up cycles,
which are discarded; the steady cycles alternate between the four (and reverse their order every
cycle), so a shared machine disturbs all alike. Each cycle times the `select_action` call that samples
a chunk. Compiled code cannot carry forward hooks, so the time per denoiser call (NFE) here is the
chunk time divided by the NFEs per chunk (N/h for SDP, N for DP): an upper bound that includes the
bookkeeping. SDP's bookkeeping is then timed on its own, eager and compiled: the same policies run
their chunks with a stand-in denoiser (one 1x1 convolution, which inductor cannot fuse with the sampler
updates around it) in place of the U-Net, so the chunk time is the bookkeeping plus s near-free calls,
an upper bound. (Subtracting s timed U-Net calls from the real chunk cannot resolve it: a 1 % spread
in a call's time times s = 50 calls is half a call.) It is reported against one U-Net call timed alone
on the streaming call's inputs, eager and compiled as the step is; run beside the real U-Net, eager
Python work also pays for the caches the U-Net evicts, which the hook-based `latency` bench includes.

The floor: one denoiser call reads every U-Net weight at least once, so it cannot take less than
(U-Net parameter bytes) / (memory bandwidth). The bandwidth is measured here, as the copy rate of a
buffer much larger than the caches (bytes read + written per second).

SDP's eager and compiled streams get the same observations and generator seeds: their actions are
compared (max abs difference, reported).
"""

import argparse
import json
import logging
import statistics
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import nn
from tqdm import tqdm

from ..observations import stack_cameras
from .latency_measure import (
    OBSERVATIONS,
    UNET_PRESETS,
    Case,
    Clock,
    Sampler,
    build_policies,
    cpu_threads,
    expected_denoiser_calls,
    observation_stream,
)
from .latency_report import environment
from .report import table

logger = logging.getLogger(__name__)
JSON_NAME = "compiled.json"
NAMES = ("sdp_eager", "sdp_compiled", "dp_eager", "dp_compiled")


def memory_bandwidth(device: torch.device, megabytes: int = 512, repeats: int = 5) -> float:
    """Bytes per second moved by copying a large buffer (read + write), median of ``repeats``."""
    src = torch.empty(megabytes * 2**20 // 4, dtype=torch.float32, device=device).uniform_()
    dst = torch.empty_like(src)
    clock, times = Clock(device), []
    for _ in range(repeats + 1):  # the first copy pages the buffers in
        start = clock.now()
        dst.copy_(src)
        times.append(clock.now() - start)
    return 2 * src.numel() * src.element_size() / statistics.median(times[1:])


def unet_bytes(policy) -> int:
    unet = policy.diffusion.unet if hasattr(policy, "diffusion") else policy.model.unet
    unet = getattr(unet, "_orig_mod", unet)
    return sum(p.numel() * p.element_size() for p in unet.parameters())


def unet_loop(unet, sample: torch.Tensor, timesteps: list[torch.Tensor], global_cond: torch.Tensor):
    """A streaming call's s U-Net calls and nothing else (no conditioning, sampler update or shift);
    each output feeds the next call, so that compilation cannot drop one."""
    for t in timesteps:
        sample = unet(sample, t, global_cond=global_cond)
    return sample


def unet_call_ms(policy, observation: dict, clock: Clock, repeats: int, compile_mode: str | None) -> float:
    """One U-Net call of SDP's streaming step alone: ``unet_loop`` on the inputs a streaming call gives
    the U-Net (buffer sample, the plan's timesteps, the observation conditioning), eager or compiled as
    one graph in ``compile_mode`` as the streaming step is; ms per call, median over ``repeats``."""
    model = policy._sampling_model()
    loop = unet_loop
    if compile_mode is not None:
        loop = torch.compile(unet_loop, mode=compile_mode, fullgraph=True, dynamic=False)
    sample = policy._buffer.sample
    timesteps = [c.timesteps for c in policy._buffer.plan(sample.device, sample.shape[0])]
    to = policy.config.n_obs_steps
    # the cameras stacked as `select_action` stacks them before they join the history
    history = {
        k: v.unsqueeze(1).expand(-1, to, *v.shape[1:])
        for k, v in stack_cameras(policy.config, observation).items()
    }
    global_cond = model.global_conditioning(history)

    def run() -> None:
        if compile_mode == "reduce-overhead":
            torch.compiler.cudagraph_mark_step_begin()
        loop(model.unet, sample, timesteps, global_cond)

    run()  # compiles
    times = []
    for _ in range(repeats):
        start = clock.now()
        run()
        times.append((clock.now() - start) / len(timesteps))
    return statistics.median(times) * 1000


class StandInUnet(nn.Module):
    """A denoiser that costs next to nothing, in the U-Net's place: one 1x1 convolution (an external
    kernel, so compilation keeps the sampler updates between calls as it does around the U-Net)."""

    def __init__(self, action_dim: int):
        super().__init__()
        self.conv = nn.Conv1d(action_dim, action_dim, 1)
        self.diffusion_step_encoder = nn.Identity()  # the policy keeps a plan's embeddings on it

    def forward(self, x: torch.Tensor, timestep: torch.Tensor, global_cond: torch.Tensor | None = None):
        return self.conv(x.transpose(1, 2)).transpose(1, 2)


@contextmanager
def stand_in_unet(policy):
    """The policy's sampling U-Net replaced by a `StandInUnet` (new stream), restored afterwards."""
    model = policy._sampling_model()
    unet = model.unet
    model.unet = StandInUnet(policy.config.action_feature.shape[0]).to(next(unet.parameters()).device)
    policy.reset()
    try:
        yield
    finally:
        model.unet = unet
        policy.reset()


def build(args: argparse.Namespace, batch_size: int) -> dict:
    case = Case(args.device, batch_size, args.sampler, args.n_chunks)
    args.compile = False
    sdp, dp = build_policies(args, case)
    args.compile = True
    sdp_compiled, dp_compiled = build_policies(args, case)  # same seed: the same weights
    return dict(zip(NAMES, (sdp, sdp_compiled, dp, dp_compiled), strict=True))


def run_batch(args: argparse.Namespace, batch_size: int, progress: tqdm) -> dict:
    policies = build(args, batch_size)
    device = torch.device(args.device)
    clock = Clock(device)
    features = OBSERVATIONS[args.obs]
    streams = {
        name: observation_stream(features, batch_size, args.device, torch.Generator().manual_seed(args.seed))
        for name in NAMES
    }
    generators = {name: torch.Generator(device) for name in NAMES if name.startswith("sdp")}
    times: dict[str, list[float]] = {name: [] for name in NAMES}
    actions: dict[str, list[torch.Tensor]] = {name: [] for name in generators}

    def cycle(name: str, record: list[float] | None) -> None:
        policy = policies[name]
        kwargs = {"generator": generators[name]} if name in generators else {}
        for i in range(args.n_action_steps):
            start = clock.now()
            action = policy.select_action(next(streams[name]), **kwargs)
            if i == 0 and record is not None:
                record.append(clock.now() - start)
            if name in actions and record is times[name]:
                actions[name].append(action.float().cpu())
        progress.update()

    with torch.inference_mode():
        for name, policy in policies.items():
            policy.reset()
            for _ in range(args.warmup_chunks):  # compiles
                cycle(name, record=None)
        for name, policy in policies.items():
            policy.reset()
            if name in generators:
                generators[name].manual_seed(args.seed)
        for step in range(args.steps):
            for name in NAMES if step % 2 else NAMES[::-1]:
                cycle(name, record=times[name])
        sdp, observation = policies["sdp_eager"], next(streams["sdp_eager"])
        unet_ms = {
            "eager": unet_call_ms(sdp, observation, clock, args.steps, None),
            "compiled": unet_call_ms(sdp, observation, clock, args.steps, sdp.model.compile_mode(device)),
        }
        out = summarise(policies, times, actions)
        bookkeeping = {}
        for mode in ("eager", "compiled"):
            name, chunks = f"sdp_{mode}", []
            with stand_in_unet(policies[name]):
                for _ in range(args.warmup_chunks):  # compiles again, around the stand-in
                    cycle(name, record=None)
                for _ in range(args.steps):
                    cycle(name, record=chunks)
            bookkeeping[mode] = statistics.median(chunks) * 1000
    return out | bookkeeping_report(bookkeeping, unet_ms)


def bookkeeping_report(bookkeeping_ms: dict, unet_ms: dict) -> dict:
    return {
        "sdp_unet_call_ms": unet_ms,
        "sdp_bookkeeping_ms": bookkeeping_ms,
        "sdp_bookkeeping_fraction_of_unet_call": {m: bookkeeping_ms[m] / unet_ms[m] for m in bookkeeping_ms},
    }


def summarise(policies: dict, times: dict[str, list[float]], actions: dict[str, list[torch.Tensor]]) -> dict:
    out = {}
    for name, policy in policies.items():
        chunk_ms = statistics.median(times[name]) * 1000
        nfe = expected_denoiser_calls(policy)
        out[name] = {
            "chunk_ms_p50": chunk_ms,
            "chunk_ms_samples": [t * 1000 for t in times[name]],
            "nfe_per_chunk": nfe,
            "per_nfe_ms": chunk_ms / nfe,
        }
    eager, compiled = torch.stack(actions["sdp_eager"]), torch.stack(actions["sdp_compiled"])
    out["sdp_compiled_speedup"] = out["sdp_eager"]["chunk_ms_p50"] / out["sdp_compiled"]["chunk_ms_p50"]
    out["dp_compiled_speedup"] = out["dp_eager"]["chunk_ms_p50"] / out["dp_compiled"]["chunk_ms_p50"]
    out["sdp_compiled_max_abs_action_diff"] = float((eager - compiled).abs().max())
    out["unet_bytes"] = unet_bytes(policies["sdp_eager"])
    return out


def markdown_table(report: dict) -> str:
    floor_ms = report["bandwidth_floor_per_nfe_ms"]
    header = [
        "obs",
        "batch",
        "sampler",
        "h",
        "SDP eager / compiled ms per chunk",
        "speedup",
        "DP eager / compiled ms",
        "speedup",
        "SDP compiled / DP compiled",
        "per-NFE compiled SDP ms",
        "floor ms",
        "x floor",
        "max abs action diff",
        "SDP U-Net call eager / compiled ms",
        "SDP bookkeeping eager / compiled ms",
        "% of a U-Net call",
    ]
    s = report["settings"]
    rows = []
    for r in report["results"]:
        per_nfe = r["sdp_compiled"]["per_nfe_ms"]
        bookkeeping = r["sdp_bookkeeping_fraction_of_unet_call"]
        sdp, dp = r["sdp_compiled"]["chunk_ms_p50"], r["dp_compiled"]["chunk_ms_p50"]
        rows.append(
            [
                s["obs"],
                r["batch_size"],
                s["sampler"],
                s["n_chunks"],
                f"{r['sdp_eager']['chunk_ms_p50']:.1f} / {sdp:.1f}",
                f"{r['sdp_compiled_speedup']:.2f}x",
                f"{r['dp_eager']['chunk_ms_p50']:.1f} / {dp:.1f}",
                f"{r['dp_compiled_speedup']:.2f}x",
                f"{sdp / dp:.3f}",
                f"{per_nfe:.2f}",
                f"{floor_ms:.2f}",
                f"{per_nfe / floor_ms:.1f}",
                f"{r['sdp_compiled_max_abs_action_diff']:.1e}",
                f"{r['sdp_unet_call_ms']['eager']:.2f} / {r['sdp_unet_call_ms']['compiled']:.2f}",
                f"{r['sdp_bookkeeping_ms']['eager']:.2f} / {r['sdp_bookkeeping_ms']['compiled']:.2f}",
                f"{100 * bookkeeping['eager']:.1f} / {100 * bookkeeping['compiled']:.1f}",
            ]
        )
    return "\n".join(table(header, rows))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add = parser.add_argument
    add("--output_dir", type=Path, default=Path("outputs/benchmarks/compiled"))
    add("--overwrite", action="store_true", help=f"replace an existing {JSON_NAME} in --output_dir")
    add("--obs", choices=sorted(OBSERVATIONS), default="state")
    add("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    add("--batch_sizes", nargs="+", type=int, default=[1, 64])
    add("--sampler", type=Sampler.parse, default=Sampler("DDIM", 16), help="e.g. DDPM100, DDIM16")
    add("--n_chunks", type=int, default=2, help="SDP's h")
    add("--steps", type=int, default=10, help="steady chunks timed per policy")
    add("--warmup_chunks", type=int, default=2, help="discarded chunk cycles per policy (compilation)")
    add("--n_obs_steps", type=int, default=2)
    add("--n_action_steps", type=int, default=8)
    add("--kernel_size", type=int, default=5)
    add("--quick", action="store_true", help="CI-sized run: tiny U-Net, batch 1, DDIM4, one timed chunk")
    add("--num_threads", type=int, help="torch CPU threads (default: torch's choice)")
    add("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> dict:
    if (args.output_dir / JSON_NAME).exists() and not args.overwrite:
        raise SystemExit(f"{args.output_dir / JSON_NAME} exists: pass --overwrite, or another --output_dir.")
    if args.steps < 1 or args.warmup_chunks < 1:
        raise SystemExit("--steps and --warmup_chunks must be >= 1 (the warm-up compiles).")
    args.output_dir.mkdir(parents=True, exist_ok=True)
    args.action_primer = "zero"
    if args.quick:
        args.batch_sizes, args.sampler, args.steps, args.warmup_chunks = [1], Sampler("DDIM", 4), 1, 1
    for name, value in UNET_PRESETS["quick" if args.quick else args.obs].items():
        setattr(args, name, value)
    with cpu_threads(args.num_threads):
        bandwidth = memory_bandwidth(torch.device(args.device))
        report = {
            "benchmark": "compiled",
            "environment": environment(argparse.Namespace(device=[args.device])),
            "settings": {k: str(v) if isinstance(v, Path | Sampler) else v for k, v in vars(args).items()},
            "memory_bandwidth_gb_s": bandwidth / 1e9,
            "results": [],
        }
        total = len(args.batch_sizes) * (len(NAMES) + 2) * (args.warmup_chunks + args.steps)
        with tqdm(total=total, unit="chunk", desc="eager vs compiled") as progress:
            for batch_size in args.batch_sizes:
                result = run_batch(args, batch_size, progress)
                report["results"].append({"batch_size": batch_size, **result})
                report["bandwidth_floor_per_nfe_ms"] = result["unet_bytes"] / bandwidth * 1000
                (args.output_dir / JSON_NAME).write_text(json.dumps(report, indent=2))
    print(markdown_table(report))
    logger.info("Wrote %s", args.output_dir / JSON_NAME)
    return report
