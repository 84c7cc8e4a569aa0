"""Statistics, JSON and the markdown table of the latency sweep (`latency.py`)."""

import argparse
import importlib.metadata
import os
import platform
from pathlib import Path

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy

from .latency_measure import Case, Cycle, expected_denoiser_calls
from .report import table

TARGET_RATIO = 1.1  # the target: SDP / DP time per chunk <= 1.1 / h

JSON_NAME = "latency.json"


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


def measured_results(results: list[dict]) -> list[dict]:
    return [r for r in results if "skipped" not in r]


def markdown_table(results: list[dict]) -> str:
    """The summary printed at the end (and pasted into docs/benchmarks.md): one row per measured case."""
    header = [
        "device",
        "batch",
        "sampler",
        "h",
        "horizon",
        "calls/chunk SDP / DP",
        "SDP chunk p50 / p95 ms",
        "DP chunk p50 / p95 ms",
        "per action p50 ms SDP / DP",
        "SDP primer ms",
        "SDP/DP (paired)",
        "target 1.1/h",
        "bookkeeping p50, % of a U-Net call, SDP / DP",
    ]
    rows = []
    for r in measured_results(results):
        sdp, dp, ratio = r["sdp"], r["dp"], r["ratio"]
        rows.append(
            [
                r["device"],
                r["batch_size"],
                r["sampler"],
                r["n_chunks"],
                r["horizon"],
                f"{sdp['denoiser_calls_per_chunk']} / {dp['denoiser_calls_per_chunk']}",
                f"{sdp['chunk_latency_ms']['p50']:.1f} / {sdp['chunk_latency_ms']['p95']:.1f}",
                f"{dp['chunk_latency_ms']['p50']:.1f} / {dp['chunk_latency_ms']['p95']:.1f}",
                f"{sdp['per_action_ms']['p50']:.2f} / {dp['per_action_ms']['p50']:.2f}",
                f"{sdp['primer']['latency_ms']:.1f}",
                f"{ratio['sdp_over_dp_chunk_p50']:.3f} ({ratio['sdp_over_dp_chunk_paired_p50']:.3f})",
                f"{ratio['target']:.3f}",
                f"{100 * sdp['bookkeeping_fraction_of_denoiser_call']['p50']:.1f} "
                f"/ {100 * dp['bookkeeping_fraction_of_denoiser_call']['p50']:.1f}",
            ]
        )
    return "\n".join(table(header, rows))
