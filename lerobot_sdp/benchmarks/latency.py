"""Latency of `select_action`: SDP against LeRobot's Diffusion Policy, same denoiser, same N.

What is compared. For every (device, batch size, sampler, h) case one SDP policy and one LeRobot
`DiffusionPolicy` are built from one set of fields: the DP config copies every field the two configs
share (U-Net size, observation encoder, scheduler, N, n_obs_steps, n_action_steps, compile...), and
DP's horizon is set to SDP's horizon for that h, so both denoise the same (B, horizon, A) sequence
with the same U-Net. That is the paper's "prediction time vs horizon" comparison: DP's cost per chunk
moves with h only through the horizon length, SDP's divides by h. The one architectural difference
left is SDP's per-slot step encoder (docs/algorithm.md, section 5), and it is part of what is timed.
Weights are random (untrained): latency does not depend on their values.

This module is the sweep and its command line; `latency_measure` times the two policies,
`latency_report` turns the timings into statistics, JSON and the table, `latency_plot` draws them.
"""

import argparse
import logging
from contextlib import ExitStack
from pathlib import Path

import torch
from tqdm import tqdm

from ..chunk_cost import CallProbe, denoisers
from .latency_measure import (
    OBSERVATIONS,
    UNET_PRESETS,
    Case,
    Clock,
    Contender,
    Sampler,
    build_policies,
    cpu_threads,
    image_encoders,
    measure,
    observation_stream,
)
from .latency_plot import PLOT_NAME, plot_h_sweep
from .latency_report import (
    JSON_NAME,
    environment,
    markdown_table,
    measured_results,
    ratios,
    settings,
    summarise,
)
from .report import write_json

logger = logging.getLogger(__name__)

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
                write_json(args.output_dir / JSON_NAME, report)  # an interrupted run keeps what is done
    write_json(args.output_dir / JSON_NAME, report)
    if measured_results(report["results"]):
        plot_h_sweep(report["results"], args.output_dir / PLOT_NAME)
        print(markdown_table(report["results"]))
    logger.info("Wrote %s", args.output_dir / JSON_NAME)
    return report
