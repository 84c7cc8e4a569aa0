"""The latency sweep's figure: time per chunk against horizon, and SDP / DP against h."""

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .latency_report import TARGET_RATIO, measured_results

PLOT_NAME = "latency_h_sweep.png"


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
