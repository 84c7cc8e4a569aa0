"""Train-step profile: where one `lerobot-train` step of SDP and of LeRobot's DP spends its time.

Builds everything with LeRobot's own factories from a training config (`make_dataset`,
`make_policy`, `make_pre_post_processors`, `make_optimizer_and_scheduler`, the EpisodeAwareSampler
and DataLoader settings `lerobot-train` uses) and times each phase of the step the way
`lerobot-train`'s `update_policy` runs it: data (waiting for the DataLoader), preprocess, forward,
backward, optimizer (gradient clipping, optimizer and lr-scheduler step), EMA (`policy.update()`,
SDP only). Both policies share the config's batch and data; DP is the one that matches the
config's SDP (`matched_dp`: every shared field, the U-Net included), at SDP's horizon (the same
denoiser input, as in the latency benchmark) or `--dp_horizon`, e.g. LeRobot's Push-T reference 16.
Output: OUTPUT_DIR/train_profile.json and a Markdown table on stdout.
"""

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from .matched_dp import matching_dp_config
from .policy_args import add_training_arguments
from .report import table, write_json

PHASES = ("data", "preprocess", "forward", "backward", "optimizer", "ema")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument("--policies", nargs="+", default=["sdp", "diffusion"], choices=["sdp", "diffusion"])
    p.add_argument("--steps", type=int, default=30, help="timed steps per policy (after --warmup)")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument(
        "--num_threads", type=int, default=1, help="torch intra-op threads of the training process"
    )
    p.add_argument("--num_workers", type=int, default=None, help="DataLoader workers (default: the config's)")
    p.add_argument("--batch_size", type=int, default=None, help="default: the config's")
    p.add_argument("--dp_horizon", type=int, default=None, help="default: SDP's horizon")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/train_profile"))


def train_config(args: argparse.Namespace, policy: str):
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
    cfg = draccus.parse(TrainPipelineConfig, config_path=str(args.config_path), args=overrides)
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


def profile_policy(args: argparse.Namespace, policy_type: str) -> dict:
    from lerobot.datasets import EpisodeAwareSampler
    from lerobot.datasets.factory import make_dataset
    from lerobot.optim.factory import make_optimizer_and_scheduler
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    cfg = train_config(args, policy_type)
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
    batches = iter(loader)
    timer = Timer({phase: [] for phase in PHASES})
    policy.train()
    for step in range(args.warmup + args.steps):
        if step == args.warmup:
            timer.seconds = {phase: [] for phase in PHASES}
        t = time.perf_counter()
        batch = next(batches)
        t = timer("data", t)
        batch = preprocessor(batch)
        t = timer("preprocess", t)
        loss, _ = policy.forward(batch)
        t = timer("forward", t)
        loss.backward()
        t = timer("backward", t)
        torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.optimizer.grad_clip_norm)
        optimizer.step()
        optimizer.zero_grad()
        if scheduler is not None:
            scheduler.step()
        t = timer("optimizer", t)
        if hasattr(policy, "update"):
            policy.update()
        timer("ema", t)
    ms = {phase: 1e3 * sum(v) / len(v) for phase, v in timer.seconds.items()}
    step_ms = sum(ms.values())
    return {
        "policy": policy_type,
        "horizon": cfg.policy.horizon,
        "batch_size": cfg.batch_size,
        "num_workers": cfg.num_workers,
        "phase_ms": ms,
        "step_ms": step_ms,
        "model_ms": step_ms - ms["data"] - ms["preprocess"],
        "samples_per_s": 1e3 * cfg.batch_size / step_ms,
    }


def markdown(rows: list[dict]) -> str:
    header = ["policy", "horizon", *(f"{p} (ms)" for p in PHASES), "step (ms)", "samples/s"]
    cells = [
        [
            r["policy"],
            r["horizon"],
            *(f"{r['phase_ms'][p]:.1f}" for p in PHASES),
            f"{r['step_ms']:.1f}",
            f"{r['samples_per_s']:.0f}",
        ]
        for r in rows
    ]
    return "\n".join(table(header, cells))


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.num_threads)
    rows = [profile_policy(args, policy) for policy in args.policies]
    report = {"num_threads": args.num_threads, "config_path": str(args.config_path), "rows": rows}
    if {"sdp", "diffusion"} <= {r["policy"] for r in rows}:
        by = {r["policy"]: r for r in rows}
        report["sdp_over_dp_model_time"] = by["sdp"]["model_ms"] / by["diffusion"]["model_ms"]
    write_json(args.output_dir / "train_profile.json", report)
    print(markdown(rows))
    if "sdp_over_dp_model_time" in report:
        ratio = report["sdp_over_dp_model_time"]
        print(f"SDP / DP model time per step (forward + backward + optimizer + EMA): {ratio:.3f}")
