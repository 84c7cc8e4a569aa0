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
Every setting below takes several values, and every policy is stepped each way (one contender per
combination), interleaved as above, so each A/B is measured in one process on one machine:
`--precision fp32 bf16` (bf16 runs the forward under autocast, as `lerobot-train
--policy.use_amp=true` does: accelerate's autocast, bf16 on CPU), `--num_threads 1 2` (torch threads,
set before each of the contender's steps), `--data memory lerobot` (the samples served from memory,
`lerobot_sdp.memory_dataset`, or by LeRobot's own reader) and `--compile eager compiled` (the
policy's training forward under `torch.compile`; its compilation happens in the warm-up steps).
Every contender's policy starts from the same weights (the config's seed), and its loss is kept at
every step: over a long run (e.g. 2,000 steps) the bins of `--loss_bin` steps show whether the
settings train alike (the loss table and loss_curves.png: each bin's mean with its standard error).
`--limit` adds the hardware's limit (`hardware_limit`): the FLOPs of a step, this machine's GEMM and
conv1d rates at each contender's threads and precision, and the step's model time against
FLOPs / rate.
Output: OUTPUT_DIR/train_profile.json (and loss_curves.png) and Markdown tables on stdout.
"""

import argparse
import itertools
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from .. import memory_dataset
from . import hardware_limit
from .matched_dp import matching_dp_config
from .policy_args import add_training_arguments, configs
from .report import save_figure, table, write_json

PHASES = ("data", "preprocess", "forward", "backward", "optimizer", "ema")
AUTOCAST = {"fp32": None, "bf16": torch.bfloat16}
CORES = len(os.sched_getaffinity(0))


@dataclass(frozen=True)
class Variant:
    """The settings one contender trains with (module docstring)."""

    precision: str = "fp32"
    threads: int = 1
    data: str = "memory"
    compile: str = "eager"

    def label(self, axes: list[str]) -> str:
        """The settings that differ between contenders, e.g. "bf16 2t"."""
        parts = asdict(self) | {"threads": f"{self.threads}t"}
        return " ".join(parts[a] for a in axes)


def variants(args: argparse.Namespace) -> tuple[list[Variant], list[str]]:
    """Every combination of the settings given, and the settings that take more than one value."""
    axes = {"precision": args.precision, "threads": args.num_threads, "data": args.data}
    axes["compile"] = args.compile
    combos = [Variant(**dict(zip(axes, values, strict=True))) for values in itertools.product(*axes.values())]
    return combos, [name for name, values in axes.items() if len(values) > 1]


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p, several_configs=True)
    p.add_argument("--policies", nargs="+", default=["sdp", "diffusion"], choices=["sdp", "diffusion"])
    p.add_argument("--steps", type=int, default=30, help="timed steps per policy (after --warmup)")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument(
        "--num_threads",
        type=int,
        nargs="+",
        default=[CORES],
        help="torch intra-op threads (default: one per core); several: every policy each way",
    )
    p.add_argument(
        "--data",
        nargs="+",
        default=["memory"],
        choices=["memory", "lerobot"],
        help="samples served from memory or by LeRobot's reader; several: every policy each way",
    )
    p.add_argument(
        "--compile",
        nargs="+",
        default=["eager"],
        choices=["eager", "compiled"],
        help="the training forward eager or under torch.compile; several: every policy each way",
    )
    p.add_argument("--limit", action="store_true", help="add the hardware's limit (FLOPs / measured rate)")
    p.add_argument("--loss_bin", type=int, default=100, help="steps per bin of the loss comparison")
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
    dataset: object
    batches: object
    timer: Timer
    variant: Variant
    forward: Callable
    losses: list[float] = field(default_factory=list)
    limit: dict = field(default_factory=dict)


def build(
    args: argparse.Namespace, config_path: Path, policy_type: str, name: str, variant: Variant = Variant()
) -> Contender:
    from lerobot.datasets import EpisodeAwareSampler
    from lerobot.datasets.factory import make_dataset
    from lerobot.optim.factory import make_optimizer_and_scheduler
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.utils.utils import cycle

    cfg = train_config(args, config_path, policy_type)
    dataset = make_dataset(cfg)
    if variant.data == "lerobot":
        memory_dataset.read_with_lerobot(dataset)
    torch.manual_seed(cfg.seed or 0)  # every contender of a config starts from the same weights
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
    forward = torch.compile(policy.forward) if variant.compile == "compiled" else policy.forward
    return Contender(
        name,
        config_path,
        cfg,
        policy,
        preprocessor,
        optimizer,
        scheduler,
        dataset,
        cycle(loader),  # endless, as lerobot-train's
        timer,
        variant,
        forward,
    )


def contender_loss(c: Contender, batch: dict, forward: Callable) -> torch.Tensor:
    """The loss of `forward` on a preprocessed batch, under autocast at the contender's precision."""
    dtype = AUTOCAST[c.variant.precision]
    device = next(c.policy.parameters()).device.type
    with torch.autocast(device, dtype=dtype, enabled=dtype is not None):
        loss, _ = forward(batch)
    return loss


def take_step(c: Contender) -> None:
    """One training step, each phase timed as `lerobot-train`'s `update_policy` runs it."""
    torch.set_num_threads(c.variant.threads)
    t = time.perf_counter()
    batch = next(c.batches)
    t = c.timer("data", t)
    batch = c.preprocessor(batch)
    t = c.timer("preprocess", t)
    loss = contender_loss(c, batch, c.forward)
    c.losses.append(loss.item())
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
    row = {
        "name": c.name,
        "policy": c.cfg.policy.type,
        "config_path": str(c.config_path),
        "horizon": c.cfg.policy.horizon,
        **asdict(c.variant),
        "batch_size": c.cfg.batch_size,
        "num_workers": c.cfg.num_workers,
        "phase_ms": ms,
        "step_ms": step_ms,
        "model_ms": step_ms - ms["data"] - ms["preprocess"],
        "samples_per_s": 1e3 * c.cfg.batch_size / step_ms,
        "losses": c.losses,
    }
    if c.limit:
        row |= c.limit | {"model_over_limit": row["model_ms"] / c.limit["limit_ms"]}
    return row


def contender_name(policy: str, path: Path, variant: Variant, n_paths: int, axes: list[str]) -> str:
    """The policy, with its config when several are compared and the settings that differ."""
    name = f"{policy} ({path.stem})" if n_paths > 1 else policy
    return f"{name} {variant.label(axes)}" if axes else name


def conv_shape(c: Contender) -> hardware_limit.ConvShape:
    """The conv1d of the U-Net's middle level: its channels at its length (the horizon halved per level)."""
    dims = c.cfg.policy.down_dims
    level = len(dims) // 2
    length = c.cfg.policy.horizon // 2**level
    return hardware_limit.ConvShape(c.cfg.batch_size, dims[level], length, c.cfg.policy.kernel_size)


def measure_limit(c: Contender, rates: dict) -> None:
    """The contender's FLOPs per step and the time they take at this machine's rate (`rates` caches the
    probes by threads, precision and shape)."""
    batch = c.preprocessor(next(c.batches))
    # eager: torch's FLOP counter sees the operators of an uncompiled forward
    flops = hardware_limit.step_flops(lambda: contender_loss(c, batch, c.policy.forward).backward())
    c.optimizer.zero_grad()
    shape = conv_shape(c)
    key = (c.variant.threads, c.variant.precision, shape)
    if key not in rates:
        dtype = AUTOCAST[c.variant.precision] or torch.float32
        rates[key] = hardware_limit.throughput(c.variant.threads, dtype, shape)
    rate = rates[key]
    c.limit = {"gflop_per_step": flops / 1e9, **rate, "limit_ms": flops / rate["peak_gflops"] / 1e6}


def profile(args: argparse.Namespace) -> list[dict]:
    """Every contender, stepped in turn (module docstring); one summary row each."""
    paths = configs(args)
    combos, axes = variants(args)
    contenders = [
        build(args, path, policy, contender_name(policy, path, variant, len(paths), axes), variant)
        for path in paths
        for policy in args.policies
        for variant in combos
    ]
    if args.limit:
        rates = {}
        for c in contenders:
            measure_limit(c, rates)
    for step in range(args.warmup + args.steps):
        if step == args.warmup:
            for c in contenders:
                c.timer.seconds = {phase: [] for phase in PHASES}
                c.losses.clear()
        for c in contenders if step % 2 == 0 else contenders[::-1]:
            take_step(c)
    rows = [summary(c) for c in contenders]
    for row in rows:
        row["model_time_vs_first"] = row["model_ms"] / rows[0]["model_ms"]
    return rows


def loss_bins(losses: list[float], size: int) -> list[tuple[float, float]]:
    """(mean, standard error) of each full bin of `size` consecutive losses."""
    bins = []
    for start in range(0, len(losses) - size + 1, size):
        values = torch.tensor(losses[start : start + size], dtype=torch.float64)
        bins.append((values.mean().item(), (values.std() / math.sqrt(size)).item()))
    return bins


def z_score(difference: float, se: float) -> float:
    """|difference| in standard errors (a difference with no spread at all is infinitely many)."""
    if se > 0:
        return abs(difference) / se
    return 0.0 if difference == 0 else math.inf


def loss_agreement(rows: list[dict], size: int) -> list[dict]:
    """Each row's binned loss against the first row's: the largest |difference| / its standard error
    over the bins (about 2 or less: equal within noise), and the mean of the last bin."""
    first = loss_bins(rows[0]["losses"], size)
    agreement = []
    for row in rows:
        bins = loss_bins(row["losses"], size)
        z = [z_score(m - m0, math.hypot(se, se0)) for (m, se), (m0, se0) in zip(bins, first, strict=True)]
        agreement.append({"name": row["name"], "bins": bins, "max_abs_z": max(z), "last_bin": bins[-1]})
    return agreement


def plot_losses(agreement: list[dict], size: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for a in agreement:
        steps = [size * (i + 0.5) for i in range(len(a["bins"]))]
        mean, se = zip(*a["bins"], strict=True)
        ax.errorbar(steps, mean, yerr=se, label=a["name"], capsize=2, marker=".")
    ax.set(xlabel="training step", ylabel=f"loss (mean of {size} steps)", yscale="log")
    ax.legend()
    save_figure(fig, path)


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


def limit_markdown(rows: list[dict]) -> str:
    header = [
        "policy",
        "GFLOP/step",
        "GEMM GFLOP/s",
        "conv1d GFLOP/s",
        "limit (ms)",
        "model (ms)",
        "model / limit",
    ]
    cells = [
        [
            r["name"],
            f"{r['gflop_per_step']:.2f}",
            f"{r['gemm_gflops']:.0f}",
            f"{r['conv1d_gflops']:.0f}",
            f"{r['limit_ms']:.1f}",
            f"{r['model_ms']:.1f}",
            f"{r['model_over_limit']:.2f}x",
        ]
        for r in rows
    ]
    return "\n".join(table(header, cells))


def loss_markdown(agreement: list[dict], size: int) -> str:
    header = ["policy", f"loss, last {size} steps", "max |diff| / SE against the first row"]
    cells = [
        [a["name"], f"{a['last_bin'][0]:.4f} ± {a['last_bin'][1]:.4f}", f"{a['max_abs_z']:.2f}"]
        for a in agreement
    ]
    return "\n".join(table(header, cells))


def run(args: argparse.Namespace) -> None:
    rows, paths = profile(args), configs(args)
    report = {"num_threads": args.num_threads, "config_path": list(map(str, paths)), "rows": rows}
    single = len(paths) == 1 and len(variants(args)[0]) == 1
    if single and {"sdp", "diffusion"} <= {r["policy"] for r in rows}:
        by = {r["policy"]: r for r in rows}
        report["sdp_over_dp_model_time"] = by["sdp"]["model_ms"] / by["diffusion"]["model_ms"]
    args.output_dir.mkdir(parents=True, exist_ok=True)
    if args.steps >= args.loss_bin:
        report["loss_agreement"] = loss_agreement(rows, args.loss_bin)
        plot_losses(report["loss_agreement"], args.loss_bin, args.output_dir / "loss_curves.png")
    write_json(args.output_dir / "train_profile.json", report)
    print(markdown(rows))
    if args.limit:
        print(limit_markdown(rows))
    if "loss_agreement" in report:
        print(loss_markdown(report["loss_agreement"], args.loss_bin))
    if "sdp_over_dp_model_time" in report:
        ratio = report["sdp_over_dp_model_time"]
        print(f"SDP / DP model time per step (forward + backward + optimizer + EMA): {ratio:.3f}")
