"""Learning curves for the quality benchmark (`lerobot-sdp-bench quality --curve_every K`).

`lerobot-train` saves a checkpoint every K steps; each one is evaluated by `lerobot-eval` on the
run's fixed episode seeds, so every point of every policy's curve sees the same episodes. Training
wall time at a checkpoint is read from `lerobot-train`'s own timestamped step logs: the intervals
between consecutive step logs of one process are summed, and steps no interval covers (the first
`log_freq` steps of each process, resumes) are charged at the run's median seconds per step, so
time spent stopped between sessions never counts.
"""

import itertools
import json
import re
import statistics
from datetime import datetime
from pathlib import Path

from .episodes import figures
from .report import reward_success_plot, save_figure

STEP_LOG = re.compile(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) .*?\bstep:(\d+(?:\.\d+)?[KM]?) ")
# lerobot-train's progress bar, printed on the same line just before a step log: "2000/18000 [07:45<...]"
# counts this process's steps out of those left, which gives the exact step (LeRobot rounds its own
# `step:2K` to a thousand, far coarser than the log interval).
PROGRESS = re.compile(r"(\d+)/(\d+) \[[^\]]*\]\s*\S+ \d{4}-\d\d-\d\d \d\d:\d\d:\d\d ")


def parse_step(token: str) -> int:
    scale = {"K": 1_000, "M": 1_000_000}.get(token[-1], 1)
    return round(float(token.rstrip("KM")) * scale)


def step_logs(train_log: Path, final_step: int | None = None) -> list[tuple[datetime, int]]:
    """(time, step) of every step log; exact from the progress bar when `final_step` (the run's
    --steps) is given, else LeRobot's rounded step."""
    if not train_log.exists():
        return []
    marks = []
    for line in train_log.read_text(errors="replace").splitlines():
        if match := STEP_LOG.search(line):
            step = parse_step(match[2])
            if final_step is not None and (bar := PROGRESS.search(line)):
                step = final_step - int(bar[2]) + int(bar[1])
            marks.append((datetime.strptime(match[1], "%Y-%m-%d %H:%M:%S"), step))
    return marks


LOSS = re.compile(r"\bloss:([0-9.eE+-]+) .*?\bsmp/s:([0-9.]+[KM]?)")


def loss_logs(train_log: Path, final_step: int) -> list[dict]:
    """Every step log's exact step, loss (LeRobot's average over the log window, over all ranks) and
    samples per second (the whole run's, all ranks), in log order."""
    points = []
    for line in train_log.read_text(errors="replace").splitlines():
        if (match := STEP_LOG.search(line)) and (loss := LOSS.search(line)):
            bar = PROGRESS.search(line)
            step = final_step - int(bar[2]) + int(bar[1]) if bar else parse_step(match[2])
            points.append({"step": step, "loss": float(loss[1]), "samples_per_s": parse_step(loss[2])})
    return points


def wall_time_at(marks: list[tuple[datetime, int]], step: int) -> float | None:
    """Training seconds spent to reach `step` (None without two step logs to measure a rate)."""
    intervals = []
    for (t0, s0), (t1, s1) in itertools.pairwise(marks):
        if s1 > s0 and t1 >= t0:
            intervals.append((s0, s1, (t1 - t0).total_seconds()))
    if not intervals:
        return None
    per_step = statistics.median(d / (s1 - s0) for s0, s1, d in intervals)
    # a gap far slower than the median is a stop between sessions, not training
    counted = [(s0, s1, d) for s0, s1, d in intervals if d <= 5 * per_step * (s1 - s0) and s1 <= step]
    covered = sum(s1 - s0 for s0, s1, _ in counted)
    return sum(d for *_, d in counted) + max(0, step - covered) * per_step


def train_wall_s(train_log: Path, steps: int, clock_s: float) -> float:
    """A run's training seconds: from its step logs as for a curve point, so that a pause or a stop
    between sessions never counts; the wall clock `clock_s` (which counts them) only for a run too
    short to log two steps."""
    logged = wall_time_at(step_logs(train_log, steps), steps)
    return clock_s if logged is None else logged


def checkpoint_steps(train_dir: Path, every: int) -> list[int]:
    """Saved checkpoints whose step is a multiple of `every`, ascending."""
    root = train_dir / "checkpoints"
    steps = [int(p.name) for p in root.iterdir() if p.name.isdigit()] if root.exists() else []
    return sorted(s for s in steps if s % every == 0)


def episode_stats(eval_dir: Path) -> dict:
    """avg_max_reward and pc_success with their standard errors, from lerobot-eval's eval_info.json."""
    info = json.loads((eval_dir / "eval_info.json").read_text())
    max_rewards, successes = [], []
    for task in info.get("per_task", []):
        max_rewards += task["metrics"]["max_rewards"]
        successes += task["metrics"]["successes"]
    if len(max_rewards) < 2:
        overall = info["overall"]
        return {
            "avg_max_reward": overall["avg_max_reward"],
            "pc_success": overall["pc_success"],
            "n_episodes": len(max_rewards),
        }
    return figures(max_rewards, successes)


def plot(rows: dict[str, dict], path: Path, title: str) -> None:
    """avg_max_reward and pc_success against training steps and training wall time, one line per
    policy, the evaluation latency per chunk in the legend."""
    series = {
        f"{name} ({row['denoiser_calls_per_chunk']:g} calls, {row['latency_per_chunk_ms']:.0f} ms / chunk "
        "at batch 1)": row["curve"]
        for name, row in rows.items()
        if row.get("curve")
    }
    x_axes = [("step", "training steps", 1), ("train_wall_s", "training wall time (min)", 60)]
    fig, _ = reward_success_plot(series, x_axes, title)
    save_figure(fig, path)
