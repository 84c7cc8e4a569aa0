"""What every benchmark writes: markdown tables of formatted cells, figures with their standard
errors, and the JSON result file (written after every cell, so a stopped run keeps what it measured)."""

import json
from collections.abc import Iterable, Sequence
from pathlib import Path


def table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    """Markdown table lines: the header, its separator, one line per row of already formatted cells."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows]


def with_se(row: dict, key: str, digits: int) -> str:
    """`row[key]` with its standard error (`row[key + "_se"]`) when the row has one."""
    value = f"{row[key]:.{digits}f}"
    return f"{value} ± {row[key + '_se']:.{digits}f}" if key + "_se" in row else value


def write_json(path: Path, report: dict) -> None:
    """The report as indented JSON (paths and other objects written as their str)."""
    path.write_text(json.dumps(report, indent=2, default=str))


METRICS = (("avg_max_reward", "avg_max_reward"), ("pc_success", "success (%)"))


def reward_success_plot(
    series: dict[str, list[dict]],
    x_axes: Sequence[tuple[str, str, float]],
    title: str,
    annotate: str | None = None,
    log_x: bool = False,
):
    """The benchmarks' figure: avg_max_reward (top row) and success (bottom row), each with its
    standard error, against every x of ``x_axes`` ((key, label, divisor): one column each), one line
    per entry of ``series`` (label -> points, dicts with the x keys and the metrics). ``annotate``
    names a point key written beside each point. Returns (figure, axes (2, columns)) for a caller
    to mark up, then `save_figure`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        2, len(x_axes), figsize=(max(8.0, 5.5 * len(x_axes)), 7.5), sharey="row", squeeze=False
    )
    for label, points in series.items():
        for col, (x_key, _, divisor) in enumerate(x_axes):
            xs = [p[x_key] / divisor for p in points]
            for row, (y_key, _) in enumerate(METRICS):
                ys = [p[y_key] for p in points]
                errs = [p.get(f"{y_key}_se", 0.0) for p in points]
                axes[row, col].errorbar(xs, ys, yerr=errs, marker="o", capsize=3, label=label)
                if annotate:
                    for p, x, y in zip(points, xs, ys, strict=True):
                        axes[row, col].annotate(
                            p[annotate], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points"
                        )
    for col, (_, x_label, _) in enumerate(x_axes):
        axes[1, col].set_xlabel(x_label)
    for row, (_, y_label) in enumerate(METRICS):
        axes[row, 0].set_ylabel(y_label)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    if log_x:
        for col, (x_key, _, divisor) in enumerate(x_axes):
            xs = [p[x_key] / divisor for points in series.values() for p in points]
            for ax in axes[:, col]:
                log_ticks_at(ax, xs)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig, axes


def log_ticks_at(ax, xs: Sequence[float], min_ratio: float = 1.5) -> None:
    """A log x axis labelled at the points' own x values, each at least `min_ratio` times the last
    label so that none overlap, without matplotlib's minor-tick labels (which overlap when the axis
    spans less than a decade or two)."""
    from matplotlib.ticker import FixedLocator, NullLocator

    ticks = []
    for x in sorted(xs):
        if not ticks or x >= ticks[-1] * min_ratio:
            ticks.append(x)
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(lambda x, _: f"{x:.3g}")
    ax.xaxis.set_minor_locator(NullLocator())


def save_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
