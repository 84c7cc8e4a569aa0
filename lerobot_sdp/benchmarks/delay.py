"""Task success against inference delay on Push-T, on a virtual clock (reproducible).

    lerobot-sdp-bench delay --policy sdp=PATH/pretrained_model --policy dp=PATH/pretrained_model \\
        --delays 0 1 2 3 4 6 --n_episodes 100 --output_dir outputs/benchmarks/delay

Every policy runs Push-T (gym-pusht, keypoint observations) through LeRobot's own evaluation rollout
(`lerobot_eval.eval_policy`, batched sync envs, episode seeds from `--seed`, the same for every row)
with its chunks delayed by d control ticks (`virtual_clock.DelayedControl`): LeRobot's `diffusion`
blocking and naive async, SDP naive async and, when trained with `max_delay`, delay-aware. Inference
costs nothing on that clock, so a row's figures depend on the delay alone; each policy's real delay
on this machine (its chunk latency at batch 1, in ticks at 10 Hz) is measured separately and marked.

Output: OUTPUT_DIR/results.json (written after every cell, so `--resume` goes on where a run
stopped), results.md (avg_max_reward and success with standard errors per row and delay) and
delay.png (both against d, the measured delays marked).
"""

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import torch
from lerobot.envs.configs import PushtEnv
from lerobot.envs.factory import make_env, make_env_pre_post_processors
from lerobot.policies.factory import make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy
from tqdm import tqdm

from ..chunk_cost import load_policy, stream_cost
from ..pusht.evaluation import EVAL_SEED, OBS_TYPE
from .episodes import figures
from .policy_args import add_policy_argument, parse_policies
from .report import reward_success_plot, save_figure, table, write_json
from .virtual_clock import HISTORIES, MODES, DelayedControl, mode_problem

FPS = 10  # Push-T's control rate
DELAYS = (0, 1, 2, 3, 4, 6)
EVAL_THREADS = 1  # the virtual clock makes the figures independent of speed: leave the other core free
MODES_OF = {"diffusion": ("blocking", "naive_async"), "sdp": ("naive_async", "delay_aware")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_policy_argument(p)
    p.add_argument("--delays", type=int, nargs="+", default=list(DELAYS), help="inference delays (ticks)")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES, help="rows to run (default all)")
    p.add_argument(
        "--history",
        choices=HISTORIES,
        default="full",
        help="what a chunk is conditioned on: the last n_obs_steps frames, or the newest frame repeated "
        "(LeRobot's RTC engine)",
    )
    p.add_argument("--n_episodes", type=int, default=100)
    p.add_argument("--batch_size", type=int, default=50, help="envs stepped together")
    p.add_argument("--seed", type=int, default=EVAL_SEED, help="first episode seed (as lerobot-eval)")
    p.add_argument("--episode_length", type=int, default=None, help="Push-T's 300 unless set")
    p.add_argument("--num_threads", type=int, default=2, help="torch threads for the latency measurement")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/delay"))
    group = p.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true", help="keep the cells already in results.json")
    group.add_argument("--overwrite", action="store_true", help="start results.json over")


def rows_of(name: str, policy, history: str = "full") -> list[tuple[str, str]]:
    """(row name, mode) of one policy: its type's modes; delay-aware only when trained for it. Rows
    conditioned on the newest frame only are named so."""
    modes = MODES_OF.get(policy.config.type)
    if modes is None:
        raise SystemExit(f"--policy {name}: type {policy.config.type!r}; this bench takes diffusion or sdp.")
    if policy.config.type == "sdp" and not policy.config.max_delay:
        modes = ("naive_async",)
    suffix = ", newest frame" if history == "frame" else ""
    return [(f"{name} {mode}{suffix}", mode) for mode in modes]


def evaluate(policy, path: Path, mode: str, delay: int, args: argparse.Namespace) -> dict:
    """One cell: `args.n_episodes` episodes of `policy` in `mode` at `delay`, LeRobot's metrics."""
    env_cfg = PushtEnv(obs_type=OBS_TYPE)
    if args.episode_length:
        env_cfg.episode_length = args.episode_length
    envs = make_env(env_cfg, n_envs=min(args.batch_size, args.n_episodes), use_async_envs=False)
    env = next(iter(next(iter(envs.values())).values()))
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=policy.config, pretrained_path=str(path), preprocessor_overrides={}
    )
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=policy.config)
    control = DelayedControl(policy, mode, delay, args.history)
    torch.manual_seed(args.seed)
    start = time.monotonic()
    try:
        info = eval_policy(
            env,
            control,
            env_pre,
            env_post,
            preprocessor,
            postprocessor,
            args.n_episodes,
            start_seed=args.seed,
        )
    finally:
        env.close()
    return {
        **figures(
            [e["max_reward"] for e in info["per_episode"]], [e["success"] for e in info["per_episode"]]
        ),
        "chunks": control.chunks,
        "held_ticks": control.held_ticks,
        "wall_s": round(time.monotonic() - start, 1),
    }


def measured_delay(path: Path, num_threads: int) -> dict:
    """The policy's chunk latency at batch 1 on this machine, and that delay in control ticks."""
    previous = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        cost = stream_cost(path)
    finally:
        torch.set_num_threads(previous)
    ms = cost["latency_per_chunk_ms"]
    return {**cost, "delay_ticks": math.ceil(ms / (1000 / FPS)), "num_threads": num_threads}


def cpu_model() -> str:
    """The CPU's model name (as lscpu prints it), or the architecture where /proc/cpuinfo is absent."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.machine()


def load_results(path: Path, args: argparse.Namespace) -> dict:
    if path.exists() and not (args.resume or args.overwrite):
        raise SystemExit(f"{path} exists: pass --resume to keep its cells, --overwrite to start over.")
    if path.exists() and args.resume:
        return json.loads(path.read_text())
    return {"cells": {}, "latency": {}}


def run(args: argparse.Namespace) -> dict:
    paths = parse_policies(args.policy)
    bad = [d for d in args.delays if d < 0]
    if bad:
        raise SystemExit(f"--delays must be at least 0, got {bad}.")
    args.output_dir.mkdir(parents=True, exist_ok=True)
    results_file = args.output_dir / "results.json"
    results = load_results(results_file, args)
    settings = results.setdefault("settings", {})
    if settings and (settings["n_episodes"], settings["seed"]) != (args.n_episodes, args.seed):
        raise SystemExit(
            f"{results_file} holds cells of {settings['n_episodes']} episodes from seed {settings['seed']}: "
            "resume with the same --n_episodes and --seed, or use another --output_dir."
        )
    settings |= {
        "n_episodes": args.n_episodes,
        "seed": args.seed,
        "fps": FPS,
        "machine": f"{cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__}",
        "eval_threads": EVAL_THREADS,
    }
    settings["policies"] = settings.get("policies", {}) | {name: str(p) for name, p in paths.items()}
    policies = {name: load_policy(path) for name, path in paths.items()}
    for name, path in paths.items():  # first, while nothing else of this run competes for the CPU
        if name not in results["latency"]:
            results["latency"][name] = measured_delay(path, args.num_threads)
            write_json(results_file, results)
    torch.set_num_threads(EVAL_THREADS)
    cells = [
        (name, row, mode, d)
        for name, policy in policies.items()
        for row, mode in rows_of(name, policy, args.history)
        if mode in args.modes
        for d in args.delays
    ]
    for name, row, mode, d in tqdm(cells, desc="delay bench cells"):
        key = f"{row} @ {d}"
        if key in results["cells"]:
            continue
        problem = mode_problem(policies[name], mode, d)
        results["cells"][key] = (
            {"row": row, "delay": d, "skipped": problem}
            if problem
            else {"row": row, "delay": d, **evaluate(policies[name], paths[name], mode, d, args)}
        )
        write_json(results_file, results)
    (args.output_dir / "results.md").write_text(markdown(results))
    plot(results, args.output_dir / "delay.png")
    print(markdown(results))
    return results


def table_rows(results: dict) -> dict[str, dict[int, dict]]:
    rows: dict[str, dict[int, dict]] = {}
    for cell in results["cells"].values():
        rows.setdefault(cell["row"], {})[cell["delay"]] = cell
    return rows


def markdown(results: dict) -> str:
    delays = sorted({c["delay"] for c in results["cells"].values()})
    settings = results["settings"]
    out = [
        f"Push-T, {settings['n_episodes']} episodes per cell (seeds from {settings['seed']}), "
        f"{settings['fps']} Hz, inference delay d in control ticks on a virtual clock; "
        f"{settings['machine']}.",
        "",
    ]

    def cell_text(cell: dict | None) -> str:
        if cell is None:
            return ""
        if "skipped" in cell:
            return "n/a"
        return (
            f"{cell['avg_max_reward']:.3f} ± {cell['avg_max_reward_se']:.3f} / "
            f"{cell['pc_success']:.0f} ± {cell['pc_success_se']:.0f} %"
        )

    rows = table_rows(results).items()
    out += table(
        ["row", *(f"d = {d}" for d in delays)], [[r, *(cell_text(c.get(d)) for d in delays)] for r, c in rows]
    )
    out += ["", "Each cell: avg_max_reward ± s.e. / success ± s.e.", ""]
    out += table(
        ["policy", "denoiser calls / chunk", "latency / chunk (batch 1)", "delay on this machine"],
        [
            [
                name,
                f"{lat['denoiser_calls_per_chunk']:g}",
                f"{lat['latency_per_chunk_ms']:.0f} ms ({lat['num_threads']} threads)",
                f"{lat['delay_ticks']} ticks",
            ]
            for name, lat in results["latency"].items()
        ],
    )
    return "\n".join(out) + "\n"


def plot(results: dict, path: Path) -> None:
    """avg_max_reward and success against d, one line per row; dashed: each policy's measured delay."""
    series = {
        row: [c for _, c in sorted(by_delay.items()) if "skipped" not in c]
        for row, by_delay in table_rows(results).items()
    }
    x_axes = [("delay", "inference delay d (control ticks at 10 Hz)", 1)]
    title = "Push-T under inference delay (virtual clock); dashed: each policy's delay on this CPU"
    fig, axes = reward_success_plot({row: points for row, points in series.items() if points}, x_axes, title)
    for i, (name, lat) in enumerate(results["latency"].items()):
        x = lat["delay_ticks"] + 0.04 * i
        for ax in axes[:, 0]:
            ax.axvline(x, ls="--", lw=1, color=f"C{i + 5}")
        axes[0, 0].text(
            x,
            0.02 + 0.06 * i,
            f" {name}: {lat['latency_per_chunk_ms']:.0f} ms",
            transform=axes[0, 0].get_xaxis_transform(),
            fontsize=8,
            color=f"C{i + 5}",
        )
    save_figure(fig, path)
