"""Data parallel: P processes at batch B against one process at batch P x B, shown to train the same.

Three `lerobot-train` runs of one config on one dataset, the same number of optimizer steps:

- `single_<s0>`: one process, batch P x B, seed s0;
- `single_<s1>`: the same with seed s1: its distance to the first is the run-to-run noise;
- `parallel_<s0>`: P processes under torchrun (gloo on CPU, NCCL on GPUs), batch B each, seed s0.

Reported: the loss curves (LeRobot's loss, averaged over each log window and over the ranks) and
their mean distance after warm-up, the EMA's update count in each final checkpoint, samples per
second, and each final checkpoint's success on the same `lerobot-eval` episodes. Runs resume where
they stopped (rerun the same command). Results: OUTPUT_DIR/data_parallel.json, .md and loss.png.
"""

import argparse
import statistics
import time
from pathlib import Path

from ..lerobot_cli import evaluate, train, trained_steps
from ..pusht.evaluation import EVAL_SEED, OBS_TYPE, pusht_eval_args
from .curves import episode_stats, loss_logs, train_wall_s
from .policy_args import add_training_arguments
from .report import save_figure, table, with_se, write_json

WARMUP_FRACTION = 0.1  # loss windows before this share of the steps are left out of the distances
# The parallel run is "within the noise" when its loss curve lies no further from the one-process
# runs than those lie from each other, with this much room (three runs give one noise sample).
NOISE_ROOM = 1.5


def after_warmup(steps: int) -> float:
    return WARMUP_FRACTION * steps


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument("--processes", type=int, default=2, help="processes of the parallel run (P)")
    p.add_argument("--batch_size", type=int, default=32, help="batch per process of the parallel run (B)")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--seeds", type=int, nargs=2, default=[1000, 2000], help="s0 (both kinds) and s1")
    p.add_argument("--log_freq", type=int, default=50)
    p.add_argument("--num_workers", type=int, default=None, help="DataLoader workers per process")
    p.add_argument("--eval_episodes", type=int, default=50)
    p.add_argument("--device", default="cpu")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/data_parallel"))


def runs(args: argparse.Namespace) -> dict[str, dict]:
    """name -> (processes, batch per process, seed)."""
    s0, s1 = args.seeds
    p, b = args.processes, args.batch_size
    return {
        f"single_{s0}": {"processes": 1, "batch_size": p * b, "seed": s0},
        f"single_{s1}": {"processes": 1, "batch_size": p * b, "seed": s1},
        f"parallel_{s0}": {"processes": p, "batch_size": b, "seed": s0},
    }


def train_args(args: argparse.Namespace, spec: dict) -> list[str]:
    out = [
        f"--config_path={args.config_path}",
        f"--dataset.repo_id={args.repo_id}",
        f"--dataset.root={args.dataset_root}",
        f"--batch_size={spec['batch_size']}",
        f"--seed={spec['seed']}",
        f"--log_freq={args.log_freq}",
        f"--save_freq={args.steps}",
        f"--policy.device={args.device}",
        "--wandb.enable=false",
    ]
    return out + ([f"--num_workers={args.num_workers}"] if args.num_workers is not None else [])


def ema_updates(model_dir: Path) -> int | None:
    """The `update()` count saved in an SDP checkpoint (`ema_step`: one per optimiser step, with or
    without EMA); None for a policy that keeps none (LeRobot's DP)."""
    from safetensors import safe_open

    with safe_open(str(model_dir / "model.safetensors"), "pt") as f:
        return int(f.get_tensor("ema_step")) if "ema_step" in f.keys() else None  # noqa: SIM118


def execute(args: argparse.Namespace, name: str, spec: dict) -> dict:
    """Train (or resume, or reuse) and evaluate one run; its row."""
    root = args.output_dir / "runs" / name
    t0 = time.monotonic()
    log = root / "train.log"
    model_dir = train(root / "train", train_args(args, spec), args.steps, log, processes=spec["processes"])
    curve = loss_logs(log, args.steps)
    rates = [p["samples_per_s"] for p in curve[1:]] or [p["samples_per_s"] for p in curve]
    eval_args = pusht_eval_args(OBS_TYPE, args.eval_episodes, EVAL_SEED, args.device)
    evaluate(model_dir, root / "eval", eval_args, root / "eval.log")
    return {
        **spec,
        "global_batch": spec["processes"] * spec["batch_size"],
        "steps": trained_steps(root / "train"),
        "ema_updates": ema_updates(model_dir),
        "train_wall_s": train_wall_s(log, args.steps, time.monotonic() - t0),
        "samples_per_s": statistics.median(rates) if rates else None,
        "final_loss": statistics.fmean(p["loss"] for p in curve[-5:]) if curve else None,
        "curve": curve,
        **episode_stats(root / "eval"),
        "model_dir": model_dir,
    }


def curve_distance(a: list[dict], b: list[dict], after_step: float) -> float:
    """Mean |loss_a - loss_b| over the log windows both curves have, after `after_step`."""
    la = {p["step"]: p["loss"] for p in a if p["step"] > after_step}
    lb = {p["step"]: p["loss"] for p in b if p["step"] > after_step}
    common = sorted(la.keys() & lb.keys())
    if not common:
        raise ValueError("the two loss curves share no logged step after warm-up")
    return statistics.fmean(abs(la[s] - lb[s]) for s in common)


def verdict(rows: dict[str, dict], steps: int) -> dict:
    """The parallel run against the two one-process runs: loss distances and success differences."""
    (s0, r0), (s1, r1), (par, rp) = rows.items()
    after = after_warmup(steps)
    noise = curve_distance(r0["curve"], r1["curve"], after)
    to_single = [curve_distance(rp["curve"], r["curve"], after) for r in (r0, r1)]
    out = {
        "loss_distance_between_single_runs": noise,
        f"loss_distance_{par}_to_{s0}": to_single[0],
        f"loss_distance_{par}_to_{s1}": to_single[1],
        "loss_within_noise": max(to_single) <= NOISE_ROOM * noise,
        "ema_once_per_step": all(r["ema_updates"] in (None, r["steps"]) for r in rows.values()),
    }
    for key in ("pc_success", "avg_max_reward"):
        diff = rp[key] - r0[key]
        se = (rp.get(f"{key}_se", 0.0) ** 2 + r0.get(f"{key}_se", 0.0) ** 2) ** 0.5
        out[f"{key}_{par}_minus_{s0}"] = diff
        out[f"{key}_difference_se"] = se
        out[f"{key}_within_one_se"] = abs(diff) <= se
    return out


def markdown(rows: dict[str, dict], result: dict, args: argparse.Namespace) -> str:
    header = ["run", "processes x batch", "seed", "steps", "EMA updates", "final loss", "samples/s"]
    header += ["train min", "success (%)", "avg_max_reward"]
    cells = [
        [
            name,
            f"{r['processes']} x {r['batch_size']}",
            r["seed"],
            r["steps"],
            r["ema_updates"],
            f"{r['final_loss']:.4f}",
            f"{r['samples_per_s']:.0f}",
            f"{r['train_wall_s'] / 60:.1f}",
            with_se(r, "pc_success", 1),
            with_se(r, "avg_max_reward", 3),
        ]
        for name, r in rows.items()
    ]
    lines = [f"# Data parallel: {args.config_path.name}, {args.steps} steps", "", *table(header, cells), ""]
    lines += [f"- {k}: {v:.4f}" if isinstance(v, float) else f"- {k}: {v}" for k, v in result.items()]
    lines += [
        "",
        f"Loss distances: mean |difference| of the logged losses after step {after_warmup(args.steps):.0f}.",
    ]
    return "\n".join(lines) + "\n"


def loss_plot(rows: dict[str, dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, r in rows.items():
        ax.plot([p["step"] for p in r["curve"]], [p["loss"] for p in r["curve"]], label=name)
    ax.set(xlabel="optimizer step", ylabel="training loss (log-window average)", yscale="log", title=title)
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)


def run(args: argparse.Namespace) -> dict:
    if args.processes < 2:
        raise SystemExit(f"--processes must be at least 2 (the parallel run), got {args.processes}.")
    args.output_dir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    report = {"config": args.config_path, "args": vars(args), "runs": rows}
    for name, spec in runs(args).items():
        rows[name] = execute(args, name, spec)
        write_json(args.output_dir / "data_parallel.json", report)
    report["verdict"] = verdict(rows, args.steps)
    write_json(args.output_dir / "data_parallel.json", report)
    (args.output_dir / "data_parallel.md").write_text(markdown(rows, report["verdict"], args))
    loss_plot(rows, args.output_dir / "loss.png", f"{args.config_path.name}: {args.processes} processes vs 1")
    print((args.output_dir / "data_parallel.md").read_text(), flush=True)
    return report
