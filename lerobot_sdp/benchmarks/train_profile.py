"""Train-step profile: where one `lerobot-train` step of SDP and of LeRobot's DP spends its time.

Builds everything with LeRobot's own factories from a training config (`make_dataset`,
`make_policy`, `make_pre_post_processors`, `make_optimizer_and_scheduler`, the EpisodeAwareSampler
and DataLoader settings `lerobot-train` uses) and times each phase of the step the way
`lerobot-train`'s `update_policy` runs it: data (waiting for the DataLoader), preprocess, forward,
backward, optimizer (gradient clipping, optimizer and lr-scheduler step), EMA (`policy.update()`,
SDP only). Both policies share the config's batch and data; DP is the one that matches the
config's SDP (`matched_dp`: every shared field, the U-Net included), at SDP's horizon (the same
denoiser input, as in the latency benchmark) or `--dp_horizon`, e.g. LeRobot's Push-T reference 16.

Every policy of every config (`--config_path` takes several, e.g. the same recipe with and without
`max_delay`) is built first, then they take their steps in turn, one step each per round (the order
reversed every other round), so that a machine whose speed drifts over minutes slows them all alike
and the ratios between them hold; each row's model time is also given relative to the first row's.
`--precision fp32 bf16` steps every policy both ways: bf16 runs the forward under autocast, as
`lerobot-train --policy.use_amp=true` does (accelerate's autocast; bf16 on CPU).
Output: OUTPUT_DIR/train_profile.json and a Markdown table on stdout.
"""

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from .matched_dp import matching_dp_config
from .policy_args import add_training_arguments, configs
from .report import table, write_json

PHASES = ("data", "preprocess", "forward", "backward", "optimizer", "ema")
AUTOCAST = {"fp32": None, "bf16": torch.bfloat16}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p, several_configs=True)
    p.add_argument("--policies", nargs="+", default=["sdp", "diffusion"], choices=["sdp", "diffusion"])
    p.add_argument("--steps", type=int, default=30, help="timed steps per policy (after --warmup)")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument(
        "--num_threads", type=int, default=1, help="torch intra-op threads of the training process"
    )
    p.add_argument("--num_workers", type=int, default=None, help="DataLoader workers (default: the config's)")
    p.add_argument("--batch_size", type=int, default=None, help="default: the config's")
    p.add_argument("--dp_horizon", type=int, default=None, help="default: SDP's horizon")
    p.add_argument(
        "--precision",
        nargs="+",
        default=["fp32"],
        choices=list(AUTOCAST),
        help="bf16: the forward under autocast (`--policy.use_amp=true`); several: every policy each way",
    )
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/train_profile"))


def train_config(args: argparse.Namespace, config_path: Path, policy: str):
    """The config's TrainPipelineConfig; for DP, the DP that matches its SDP (`matched_dp`)."""
    import draccus
    from lerobot.configs.train import TrainPipelineConfig

    overrides = [
        f"--dataset.repo_id={args.repo_id}",
        f"--dataset.root={args.dataset_root}",
        "--wandb.enable=false",
    ]
    if args.num_workers is not None:
        overrides.append(f"--num_workers={args.num_workers}")
    if args.batch_size is not None:
        overrides.append(f"--batch_size={args.batch_size}")
    cfg = draccus.parse(TrainPipelineConfig, config_path=str(config_path), args=overrides)
    cfg.validate()
    if policy == "diffusion":
        cfg.policy = matching_dp_config(cfg.policy, args.dp_horizon)
    return cfg


@dataclass
class Timer:
    seconds: dict

    def __call__(self, phase: str, start: float) -> float:
        now = time.perf_counter()
        self.seconds[phase].append(now - start)
        return now


@dataclass
class Contender:
    """One policy of one config, built as `lerobot-train` builds it, stepped one step at a time."""

    name: str
    config_path: Path
    cfg: object
    policy: torch.nn.Module
    preprocessor: object
    optimizer: torch.optim.Optimizer
    scheduler: object
    batches: object
    timer: Timer
    precision: str = "fp32"


def build(
    args: argparse.Namespace, config_path: Path, policy_type: str, name: str, precision: str = "fp32"
) -> Contender:
    from lerobot.datasets import EpisodeAwareSampler
    from lerobot.datasets.factory import make_dataset
    from lerobot.optim.factory import make_optimizer_and_scheduler
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    cfg = train_config(args, config_path, policy_type)
    dataset = make_dataset(cfg)
    policy = make_policy(cfg.policy, ds_meta=dataset.meta)
    preprocessor, _ = make_pre_post_processors(cfg.policy, dataset_stats=dataset.meta.stats)
    optimizer, scheduler = make_optimizer_and_scheduler(cfg, policy)
    sampler = EpisodeAwareSampler(
        dataset.meta.episodes["dataset_from_index"],
        dataset.meta.episodes["dataset_to_index"],
        drop_n_last_frames=getattr(cfg.policy, "drop_n_last_frames", 0),
        shuffle=True,
        seed=cfg.seed or 0,
    )
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=cfg.batch_size,
        sampler=sampler,
        num_workers=cfg.num_workers,
        prefetch_factor=cfg.prefetch_factor if cfg.num_workers > 0 else None,
        persistent_workers=cfg.num_workers > 0,
        drop_last=False,
    )
    policy.train()
    timer = Timer({phase: [] for phase in PHASES})
    batches = iter(loader)
    return Contender(
        name, config_path, cfg, policy, preprocessor, optimizer, scheduler, batches, timer, precision
    )


def take_step(c: Contender) -> None:
    """One training step, each phase timed as `lerobot-train`'s `update_policy` runs it."""
    t = time.perf_counter()
    batch = next(c.batches)
    t = c.timer("data", t)
    batch = c.preprocessor(batch)
    t = c.timer("preprocess", t)
    dtype = AUTOCAST[c.precision]
    device = next(c.policy.parameters()).device.type
    with torch.autocast(device, dtype=dtype, enabled=dtype is not None):
        loss, _ = c.policy.forward(batch)
    t = c.timer("forward", t)
    loss.backward()
    t = c.timer("backward", t)
    torch.nn.utils.clip_grad_norm_(c.policy.parameters(), c.cfg.optimizer.grad_clip_norm)
    c.optimizer.step()
    c.optimizer.zero_grad()
    if c.scheduler is not None:
        c.scheduler.step()
    t = c.timer("optimizer", t)
    if hasattr(c.policy, "update"):
        c.policy.update()
    c.timer("ema", t)


def summary(c: Contender) -> dict:
    ms = {phase: 1e3 * sum(v) / len(v) for phase, v in c.timer.seconds.items()}
    step_ms = sum(ms.values())
    return {
        "name": c.name,
        "policy": c.cfg.policy.type,
        "config_path": str(c.config_path),
        "horizon": c.cfg.policy.horizon,
        "precision": c.precision,
        "batch_size": c.cfg.batch_size,
        "num_workers": c.cfg.num_workers,
        "phase_ms": ms,
        "step_ms": step_ms,
        "model_ms": step_ms - ms["data"] - ms["preprocess"],
        "samples_per_s": 1e3 * c.cfg.batch_size / step_ms,
    }


def contender_name(policy: str, path: Path, precision: str, n_paths: int, n_precisions: int) -> str:
    """The policy, with its config when several are compared and its precision when several are."""
    name = f"{policy} ({path.stem})" if n_paths > 1 else policy
    return f"{name} {precision}" if n_precisions > 1 else name


def profile(args: argparse.Namespace) -> list[dict]:
    """Every contender, stepped in turn (module docstring); one summary row each."""
    paths, precisions = configs(args), args.precision
    contenders = [
        build(
            args,
            path,
            policy,
            contender_name(policy, path, precision, len(paths), len(precisions)),
            precision,
        )
        for path in paths
        for policy in args.policies
        for precision in precisions
    ]
    for step in range(args.warmup + args.steps):
        if step == args.warmup:
            for c in contenders:
                c.timer.seconds = {phase: [] for phase in PHASES}
        for c in contenders if step % 2 == 0 else contenders[::-1]:
            take_step(c)
    rows = [summary(c) for c in contenders]
    for row in rows:
        row["model_time_vs_first"] = row["model_ms"] / rows[0]["model_ms"]
    return rows


def markdown(rows: list[dict]) -> str:
    header = ["policy", "horizon", *(f"{p} (ms)" for p in PHASES), "step (ms)", "samples/s", "model time"]
    cells = [
        [
            r["name"],
            r["horizon"],
            *(f"{r['phase_ms'][p]:.1f}" for p in PHASES),
            f"{r['step_ms']:.1f}",
            f"{r['samples_per_s']:.0f}",
            f"{r['model_time_vs_first']:.3f}x",
        ]
        for r in rows
    ]
    return "\n".join(table(header, cells))


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.num_threads)
    rows, paths = profile(args), configs(args)
    report = {"num_threads": args.num_threads, "config_path": list(map(str, paths)), "rows": rows}
    if len(paths) == 1 and len(args.precision) == 1 and {"sdp", "diffusion"} <= {r["policy"] for r in rows}:
        by = {r["policy"]: r for r in rows}
        report["sdp_over_dp_model_time"] = by["sdp"]["model_ms"] / by["diffusion"]["model_ms"]
    args.output_dir.mkdir(parents=True, exist_ok=True)
    write_json(args.output_dir / "train_profile.json", report)
    print(markdown(rows))
    if "sdp_over_dp_model_time" in report:
        ratio = report["sdp_over_dp_model_time"]
        print(f"SDP / DP model time per step (forward + backward + optimizer + EMA): {ratio:.3f}")
