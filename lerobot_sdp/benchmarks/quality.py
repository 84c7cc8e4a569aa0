"""Quality: SDP against LeRobot's Diffusion Policy at equal budget, plus the paper's ablations, on
Push-T (keypoints) or a robomimic task (`--env robomimic --task Lift`, low-dim, on scripted
demonstrations recorded into the output directory unless `--dataset_repo_id` names a dataset).

Every run trains through `lerobot-train` and evaluates through `lerobot-eval` on one fixed set of
episode seeds (batched sync envs), with the same data, U-Net size, observation history, batch
size, steps, learning-rate schedule and seed for every policy. SDP is trained without EMA here
because LeRobot's Diffusion Policy has none: the two differ only in how they corrupt and sample.

`--runs screen` trains LeRobot's DP, SDP h = 2 with the default recipe and SDP h = 2 with each
candidate training recipe (docs/algorithm.md, section 10) on one schedule and recording, then probes
every final model (`probe.py`) on held-out windows: `--probe_dataset_root`, or for robomimic 20
demonstrations recorded from seed 200000 into OUTPUT_DIR/probe_data.

Runs resume where they stopped (rerun the same command); `--status` prints where each run stands.
Results: OUTPUT_DIR/results.json and OUTPUT_DIR/results.md. `--eval_seed N` evaluates the same trained
models on the episodes from seed N on (held-out episodes, for a configuration chosen on the default
ones), `--n_episodes M` on M episodes instead of the budget's: those evaluations and their report
go to `eval_seedN/` (`eval_seedN_Mepisodes/`) folders beside the default ones.
"""

import argparse
import json
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from .. import shipped_configs
from ..chunk_cost import stream_cost
from ..configuration_sdp import STEP_CONDITIONINGS
from ..geometry import ChunkGeometry
from ..lerobot_cli import (
    PRECISIONS,
    Evaluation,
    evaluate,
    evaluate_all,
    last_checkpoint,
    train,
    trained_precision,
    trained_steps,
)
from ..noise_schemes import SCHEMES as NOISE_SCHEMES
from ..pusht.data import keypoints_dataset_args
from ..pusht.evaluation import EVAL_SEED, OBS_TYPE, pusht_eval_args
from ..robomimic.demonstrators import DEMONSTRATORS
from ..robomimic.evaluation import EVAL_SEED as ROBOMIMIC_EVAL_SEED
from ..robomimic.evaluation import robomimic_eval_args
from . import cost_sweep, probe
from .curves import checkpoint_steps, episode_stats, loss_logs, plot, step_logs, train_wall_s, wall_time_at
from .matched_dp import matching_dp_flags
from .report import table, with_se, write_json

DP_HORIZON = 16  # LeRobot's reference Push-T Diffusion Policy (lerobot/diffusion_pusht), DP's robomimic one


@dataclass(frozen=True)
class Budget:
    steps: int
    batch_size: int
    down_dims: tuple[int, ...]
    embed_dim: int
    lr: float
    warmup: int
    n_episodes: int
    num_inference_steps: int = 100
    scheduler: str = "DDPM"
    episode_length: int | None = None  # None: the task's own (Push-T 300, robomimic 400)
    ablation_steps: int | None = None  # the reduced budget of the ablation runs


BUDGETS = {
    # plumbing check for the test suite: seconds, meaningless numbers
    "tiny": Budget(2, 4, (16, 32), 16, 1e-4, 0, 2, 8, "DDIM", episode_length=10, ablation_steps=2),
    # state-based keypoints Push-T on 2 CPU cores: a few hours for the comparison
    "cpu": Budget(20_000, 64, (64, 128, 256), 64, 5e-4, 500, 100, ablation_steps=3_000),
    # low-dim robomimic on 2 CPU cores, DDIM 16 as the paper's real-robot runs (the sweep adds DDPM 100)
    "robomimic_cpu": Budget(20_000, 64, (64, 128, 256), 64, 5e-4, 500, 50, 16, "DDIM", ablation_steps=3_000),
}
# and "paper": the authors' hyperparameters, read from the shipped config (`paper_budget`), for a GPU
PAPER_CONFIG = "pusht_state_paper"


def paper_budget() -> Budget:
    """The authors' hyperparameters (docs/algorithm.md, section 9) as `configs/pusht_state_paper.json`
    sets them, 100 evaluation episodes, ablations at a fifth of the steps."""
    raw = json.loads(shipped_configs.path(PAPER_CONFIG).read_text())
    policy = raw["policy"]
    return Budget(
        steps=raw["steps"],
        batch_size=raw["batch_size"],
        down_dims=tuple(policy["down_dims"]),
        embed_dim=policy["diffusion_step_embed_dim"],
        lr=policy["optimizer_lr"],
        warmup=policy["scheduler_warmup_steps"],
        n_episodes=100,
        num_inference_steps=policy["num_inference_steps"],
        scheduler=policy["noise_scheduler_type"],
        ablation_steps=raw["steps"] // 5,
    )


SCHEMES = {  # the paper's Table (b): name -> noise_schemes weights
    "chunkwise": {"chunkwise": 1.0},
    "linear": {"linear": 1.0},
    "independent": {"independent": 1.0},
    "constant": {"constant": 1.0},
    "ind67_lin33": {"independent": 0.67, "linear": 0.33},
    "ind67_cw33": {"independent": 0.67, "chunkwise": 0.33},
    "cw80_const20": {"chunkwise": 0.8, "constant": 0.2},
}
PAPER_SCHEMES = {
    "chunkwise": 0.86,
    "linear": 0.36,
    "independent": 0.85,
    "constant": 0.29,
    "ind67_lin33": 0.87,
    "ind67_cw33": 0.89,
    "cw80_const20": 0.90,
}
PAPER_PRIMERS = {"zero": 0.90, "constant": 0.90, "denoise": 0.90}


@dataclass
class Run:
    name: str
    policy_args: list[str]
    steps: int
    trains_as: str = ""  # another run whose trained model this one evaluates (primer ablation)
    eval_overrides: dict = field(default_factory=dict)

    @property
    def model_run(self) -> str:
        return self.trains_as or self.name


def policy_args(budget: Budget, policy: str, device: str, dp_horizon: int = DP_HORIZON) -> list[str]:
    """`lerobot-train` flags of the budget's SDP, or of the DP that matches it (`matched_dp`)."""
    sdp = [
        "--policy.type=sdp",
        "--policy.n_obs_steps=2",
        "--policy.n_action_steps=8",
        f"--policy.down_dims=[{','.join(map(str, budget.down_dims))}]",
        "--policy.kernel_size=5",
        f"--policy.diffusion_step_embed_dim={budget.embed_dim}",
        f"--policy.noise_scheduler_type={budget.scheduler}",
        "--policy.num_train_timesteps=100",
        f"--policy.num_inference_steps={budget.num_inference_steps}",
        f"--policy.optimizer_lr={budget.lr}",
        f"--policy.scheduler_warmup_steps={budget.warmup}",
        f"--policy.device={device}",
        "--policy.push_to_hub=false",
        "--policy.use_ema=false",
    ]
    return matching_dp_flags(sdp, dp_horizon) if policy == "diffusion" else sdp


def sdp_args(budget: Budget, device: str, n_chunks: int, schemes: dict | None = None) -> list[str]:
    # every scheme written out, unset ones at 0, so no config default leaks into a run
    weights = {name: 0.0 for name in NOISE_SCHEMES} | (schemes or SCHEMES["cw80_const20"])
    return (
        policy_args(budget, "sdp", device)
        + [f"--policy.n_chunks={n_chunks}"]
        + [f"--policy.noise_schemes.{k}={v}" for k, v in weights.items()]
    )


def comparison_runs(budget: Budget, device: str) -> list[Run]:
    return [
        Run("dp", policy_args(budget, "diffusion", device), budget.steps),
        Run("sdp_h2", sdp_args(budget, device, 2), budget.steps),
        Run("sdp_h4", sdp_args(budget, device, 4), budget.steps),
    ]


def horizon_control_runs(budget: Budget, device: str) -> list[Run]:
    """LeRobot's Diffusion Policy predicting as far ahead as SDP h = 4 and h = 2 do: is SDP's lead its
    streaming or its longer horizon? LeRobot wants DP's horizon to be a multiple of 2 ** len(down_dims),
    so each is the smallest such horizon that holds SDP's past slots and h chunks. DP keeps LeRobot's
    `drop_n_last_frames` (7): like SDP, it trains on every executed frame, the slots past an episode's
    end copy-padded."""
    runs = []
    for h in (4, 2):
        geometry = ChunkGeometry(2, 8, h, budget.num_inference_steps, downsampling=2 ** len(budget.down_dims))
        name = f"dp_horizon{geometry.horizon}"
        runs.append(Run(name, policy_args(budget, "diffusion", device, geometry.horizon), budget.steps))
    return runs


def ablation_runs(budget: Budget, device: str) -> list[Run]:
    steps = budget.ablation_steps or budget.steps
    runs = [Run(f"scheme_{name}", sdp_args(budget, device, 2, w), steps) for name, w in SCHEMES.items()]
    runs += [
        Run(f"primer_{p}", [], steps, trains_as="scheme_cw80_const20", eval_overrides={"action_primer": p})
        for p in ("zero", "constant", "denoise")
    ]
    return runs


def warmstart_runs(budget: Budget, device: str, dp_model: Path) -> list[Run]:
    """SDP h = 2 fine-tuned from the comparison's trained DP for a tenth of its steps, with the paper's
    step encoder and with per-slot FiLM, and both trained from scratch for the same steps."""
    steps = max(1, budget.steps // 10)
    base = sdp_args(budget, device, 2)
    init = [f"--policy.init_from={dp_model}"]
    film = ["--policy.step_conditioning=film_per_slot"]
    return [
        Run("warm_flatten", base + init, steps),
        Run("warm_film", base + init + film, steps),
        Run("scratch_flatten_short", base, steps),
        Run("scratch_film_short", base + film, steps),
    ]


# the probe's held-out robomimic demonstrations: seeds far from the training recording's (100000 on)
PROBE_DEMO_SEED = 200_000
PROBE_DEMOS = 20


def screen_runs(budget: Budget, device: str) -> list[Run]:
    """LeRobot's DP, SDP h = 2 with the default recipe, and SDP h = 2 with each candidate recipe, all
    on the budget's schedule: constant levels for the first quarter then the mixture, 50 % constant,
    Min-SNR-5 weights, chunk-wise levels over the whole training table, a fifth of the samples at one
    independent level per chunk (the probe's candidate: the later chunk cannot always lean on a cleaner
    neighbour), EMA (SDP only: LeRobot 0.6.1's DP has none), a ramp from constant to the mixture over
    the first half."""
    steps = budget.steps
    base = sdp_args(budget, device, 2)
    without_ema = [a for a in base if not a.startswith("--policy.use_ema=")]
    # in the order they run: the fine-tune's evidence (constant levels first) before the rest
    candidates = {
        "screen_curriculum_switch": [*base, f"--policy.noise_curriculum.constant_steps={max(1, steps // 4)}"],
        "screen_const50": sdp_args(budget, device, 2, {"constant": 0.5, "chunkwise": 0.5}),
        "screen_min_snr5": [*base, "--policy.min_snr_gamma=5.0"],
        "screen_training_table": [*base, "--policy.chunkwise_grid=training_table"],
        "screen_independent_chunks": sdp_args(
            budget, device, 2, {"constant": 0.2, "chunkwise": 0.6, "independent_chunks": 0.2}
        ),
        "screen_ema": [*without_ema, "--policy.use_ema=true"],
        "screen_curriculum_ramp": [*base, f"--policy.noise_curriculum.ramp_steps={max(1, steps // 2)}"],
    }
    runs = [Run("dp", policy_args(budget, "diffusion", device), steps), Run("sdp_h2", base, steps)]
    return runs + [Run(name, flags, steps) for name, flags in candidates.items()]


def with_step_conditioning(runs: list[Run], choice: str | None) -> list[Run]:
    """The SDP runs trained with `--policy.step_conditioning=CHOICE` (those that set none already);
    DP's runs and the runs that evaluate another's model are unchanged."""
    if choice is None:
        return runs
    flag = f"--policy.step_conditioning={choice}"

    def conditioned(run: Run) -> Run:
        sdp = "--policy.type=sdp" in run.policy_args
        if not sdp or any(a.startswith("--policy.step_conditioning=") for a in run.policy_args):
            return run
        return replace(run, policy_args=[*run.policy_args, flag])

    return [conditioned(r) for r in runs]


def with_sdp_flags(runs: list[Run], flags: list[str]) -> list[Run]:
    """The SDP runs trained with each `--policy.KEY=VALUE` of `flags` in place of their own value of
    KEY (a recipe carried to every SDP run); DP's runs are unchanged."""
    keys = {f.split("=", 1)[0] + "=" for f in flags}

    def flagged(run: Run) -> Run:
        if not flags or "--policy.type=sdp" not in run.policy_args:
            return run
        kept = [a for a in run.policy_args if not any(a.startswith(k) for k in keys)]
        return replace(run, policy_args=[*kept, *flags])

    return [flagged(r) for r in runs]


def sdp_flags(args: argparse.Namespace) -> list[str]:
    """Every `--sdp_flag`, checked: each must read `--policy.KEY=VALUE`."""
    flags = []
    for flag in args.sdp_flag or []:
        if not flag.startswith("--policy.") or "=" not in flag:
            raise SystemExit(
                f"--sdp_flag takes a lerobot-train policy flag, --policy.KEY=VALUE; got {flag!r}."
            )
        flags.append(flag)
    return flags


def dp_model(output_dir: Path) -> Path:
    """The comparison's final DP model (LeRobot's `last` checkpoint), where the warm starts begin."""
    return output_dir / "runs" / "dp" / "train" / "checkpoints" / "last" / "pretrained_model"


def model_root(output_dir: Path, run: Run) -> Path:
    """Where a run's model is trained: its own folder, or that of the run it evaluates (`trains_as`)."""
    return output_dir / "runs" / run.model_run


def run_dir(output_dir: Path, run: Run, seed_dir: str = "") -> Path:
    """Where a run's evaluations go: its folder, or its `eval_seedN` subfolder for other episodes."""
    return output_dir / "runs" / run.name / seed_dir


@dataclass(frozen=True)
class Plan:
    """What the runs of one invocation share: where they live, the data and training flags, the
    episodes they are evaluated on (`seed_dir`: the evaluations' subfolder, see `run_dir`), the
    curve's checkpoint spacing with how many evaluations run at once, and how many runs train at once."""

    output_dir: Path
    data_args: list[str]
    common: list[str]
    eval_args: list[str]
    seed_dir: str = ""
    curve_every: int | None = None
    eval_jobs: int = 1
    jobs: int = 1  # runs at once: each training gets its share of the cores
    precision: str = "fp32"  # lerobot_cli.precision_flags


def execute(run: Run, plan: Plan, echo: bool = True) -> dict:
    """Train (or resume, or reuse) and evaluate one run, and with `plan.curve_every` every K-step
    checkpoint of it on the same episodes; returns its row. `echo=False` leaves the CLIs' output in
    the run's log files only (runs in parallel)."""
    root = model_root(plan.output_dir, run)
    timing_file = root / "timing.json"
    timing = json.loads(timing_file.read_text()) if timing_file.exists() else {"train_wall_s": 0.0}
    t0 = time.monotonic()
    train_args = [*plan.data_args, *plan.common, *run.policy_args]
    model_dir = train(
        root / "train",
        train_args,
        run.steps,
        root / "train.log",
        echo,
        concurrent=plan.jobs,
        precision=plan.precision,
    )
    if not run.trains_as:
        timing["train_wall_s"] += time.monotonic() - t0
        timing_file.write_text(json.dumps(timing))
    eval_args = plan.eval_args + [f"--policy.{k}={v}" for k, v in run.eval_overrides.items()]
    here = run_dir(plan.output_dir, run, plan.seed_dir)
    # the curve's last point is the run's own evaluation, done with the others
    every = plan.curve_every
    points = curve(root, here, eval_args, every, run.steps, echo, plan.eval_jobs) if every else None
    evaluate(model_dir, here / "eval", eval_args, here / "eval.log", echo)
    cost = stream_cost(model_dir, overrides=run.eval_overrides)  # alone: no evaluation runs now
    row = {"run": run.name, **episode_stats(here / "eval"), "steps": run.steps, **cost}
    row["train_precision"] = trained_precision(model_dir)
    row["train_wall_s"] = round(train_wall_s(root / "train.log", run.steps, timing["train_wall_s"]), 1)
    losses = loss_logs(root / "train.log", run.steps) if (root / "train.log").exists() else []
    row["final_loss"] = losses[-1]["loss"] if losses else None
    if every:
        row["curve"] = points
    return row


def curve(
    root: Path,
    here: Path,
    eval_args: list[str],
    every: int,
    final_step: int,
    echo: bool = True,
    jobs: int = 1,
) -> list[dict]:
    """Every saved K-step checkpoint of the model trained in `root` (`model_root`), evaluated on the
    run's episodes (the last is the run's eval), `jobs` evaluations at once."""
    steps = checkpoint_steps(root / "train", every)
    eval_dirs = {s: here / "eval" if s == final_step else here / "curve" / f"{s:06d}" for s in steps}
    checkpoints = root / "train" / "checkpoints"
    evaluate_all(
        [
            Evaluation(checkpoints / f"{s:06d}" / "pretrained_model", d, eval_args, d.with_suffix(".log"))
            for s, d in eval_dirs.items()
        ],
        jobs,
        echo,
    )
    marks = step_logs(root / "train.log", final_step)
    points = []
    for step in steps:
        wall = wall_time_at(marks, step)
        points.append(
            {"step": step, "train_wall_s": round(wall, 1) if wall else 0.0, **episode_stats(eval_dirs[step])}
        )
    return points


def status(runs: list[Run], output_dir: Path, seed_dir: str = "") -> list[str]:
    lines = []
    for run in runs:
        done = trained_steps(model_root(output_dir, run) / "train")
        evaluated = (run_dir(output_dir, run, seed_dir) / "eval" / "eval_info.json").exists()
        state = (
            "evaluated" if evaluated else ("trained" if done >= run.steps else f"training {done}/{run.steps}")
        )
        lines.append(f"{run.name:24s} {state}")
    return lines


def markdown(rows: dict[str, dict], budget_name: str, budget: Budget) -> str:
    header = [
        "run",
        "avg_max_reward",
        "pc_success",
        "paper score",
        "denoiser calls / chunk",
        "eval latency / chunk (ms, CPU, batch 1)",
        "train wall (s)",
        "steps",
        "episodes",
    ]

    def cells(name, row, paper=""):
        return [
            name,
            with_se(row, "avg_max_reward", 3),
            with_se(row, "pc_success", 1),
            paper,
            f"{row['denoiser_calls_per_chunk']:g}",
            f"{row['latency_per_chunk_ms']:.1f}",
            f"{row['train_wall_s']:.0f}",
            row["steps"],
            row["n_episodes"],
        ]

    compared = [n for n in ("dp", "sdp_h2", "sdp_h4") if n in rows] + [
        n for n in rows if n.startswith("dp_horizon")
    ]
    out = [f"Budget `{budget_name}`: {asdict(budget)}", "", "### Comparison", ""]
    out += table(header, [cells(n, rows[n]) for n in compared])
    warm = [n for n in rows if n.startswith(("warm_", "scratch_"))]
    if warm:
        out += ["", "### Warm start from the trained DP (SDP h = 2, a tenth of DP's steps)", ""]
        out += table(header, [cells(n, rows[n]) for n in ("dp", "sdp_h2", *warm) if n in rows])
    ablations = [n for n in rows if n.startswith(("scheme_", "primer_"))]
    if ablations:
        paper = {f"scheme_{k}": v for k, v in PAPER_SCHEMES.items()} | {
            f"primer_{k}": v for k, v in PAPER_PRIMERS.items()
        }
        out += ["", f"### Ablations (reduced budget: {budget.ablation_steps} steps)", ""]
        out += table(header, [cells(n, rows[n], f"{paper[n]:.2f}") for n in ablations])
    out += screen_markdown(rows, budget.steps)
    curves = [n for n in rows if rows[n].get("curve")]
    if curves:
        out += ["", "### Learning curves (every checkpoint on the same episodes)", ""]
        out += table(
            ["run", "step", "train wall (min)", "avg_max_reward", "pc_success", "episodes"],
            [
                [
                    n,
                    p["step"],
                    f"{p['train_wall_s'] / 60:.1f}",
                    with_se(p, "avg_max_reward", 3),
                    with_se(p, "pc_success", 1),
                    p["n_episodes"],
                ]
                for n in curves
                for p in rows[n]["curve"]
            ],
        )
    return "\n".join(out) + "\n"


def screen_markdown(rows: dict[str, dict], steps: int) -> list[str]:
    """The screen's table (DP, SDP h = 2 and the candidates), or nothing without a screen run."""
    screened = [n for n in rows if n.startswith("screen_")]
    if not screened:
        return []

    def cells(name: str, row: dict) -> list:
        wall = row["train_wall_s"]
        return [
            name,
            with_se(row, "pc_success", 1),
            f"{row['denoiser_calls_per_chunk']:g}",
            f"{wall:.0f}",
            f"{row['steps'] / wall:.2f}" if wall else "-",
            "-" if row.get("final_loss") is None else f"{row['final_loss']:.4f}",
            row["n_episodes"],
        ]

    header = ["run", "pc_success", "denoiser calls / chunk", "train wall (s)", "steps / s", "final loss"]
    out = ["", f"### Screen of the training recipes ({steps} steps each)", ""]
    out += [
        "SDP h = 2 throughout; `screen_ema` alone trains with EMA (LeRobot 0.6.1's DP has none). The loss "
        "is lerobot-train's last logged value: Min-SNR weights change what it measures.",
        "",
    ]
    return out + table(
        [*header, "episodes"], [cells(n, rows[n]) for n in ("dp", "sdp_h2", *screened) if n in rows]
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--budget", choices=[*BUDGETS, "paper"], default=None, help="default: cpu (Push-T), robomimic_cpu"
    )
    parser.add_argument("--env", choices=["pusht", "robomimic"], default="pusht")
    parser.add_argument("--task", choices=sorted(DEMONSTRATORS), default="Lift", help="the robomimic task")
    parser.add_argument(
        "--num_demos",
        type=int,
        default=200,
        help="scripted robomimic demonstrations to record (and train on)",
    )
    parser.add_argument(
        "--runs",
        choices=["comparison", "horizon_control", "ablations", "warmstart", "screen", "all"],
        default="comparison",
        help="horizon_control: DP at SDP h = 4's and h = 2's horizons; "
        "warmstart: SDP fine-tuned from the comparison's trained DP (run the comparison first); "
        "screen: DP and SDP h = 2 with each candidate training recipe, then the probe (not part of all)",
    )
    parser.add_argument(
        "--probe_dataset_root",
        type=Path,
        default=None,
        help="held-out LeRobotDataset the screen's probe runs on (default for robomimic: "
        f"{PROBE_DEMOS} demonstrations recorded from seed {PROBE_DEMO_SEED} into OUTPUT_DIR/probe_data)",
    )
    parser.add_argument("--probe_repo_id", default="local/probe", help="the repo_id of --probe_dataset_root")
    parser.add_argument(
        "--only",
        nargs="+",
        default=None,
        metavar="RUN",
        help="train and evaluate only these runs of the run set (e.g. `--only sdp_h4` to train one "
        "policy longer in its own output directory); other rows already in results.json stay",
    )
    parser.add_argument("--output_dir", type=Path, default=None, help="default: outputs/quality_<budget>")
    parser.add_argument(
        "--zarr", type=Path, default=None, help="Push-T zarr (default: $SDP_PUSHT_ZARR, ../shared/...)"
    )
    parser.add_argument(
        "--dataset_repo_id", default=None, help="use this LeRobotDataset instead (with --dataset_root)"
    )
    parser.add_argument("--dataset_root", type=Path, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="fp32",
        help="every training's precision (a resumed run keeps its own); fp32 by default, as every "
        "published comparison; auto: bf16 autocast on a CPU with native bf16 (avx512_bf16, AMX)",
    )
    parser.add_argument("--status", action="store_true", help="print where each run stands and exit")
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="train every run this many steps instead of the budget's (a reduced budget, labelled so)",
    )
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="then evaluate the comparison's final models at several samplers (cost.png)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="train and evaluate this many runs at once, their output in their log files only; each "
        "training without DataLoader workers gets cores / JOBS torch threads (--jobs 2 on a 2-core "
        "CPU: one thread each)",
    )
    parser.add_argument(
        "--eval_jobs",
        type=int,
        default=1,
        help="run this many lerobot-eval at once for the learning curves and the sweep (each uses one "
        "core; 2 on a 2-core CPU when nothing trains beside them)",
    )
    parser.add_argument(
        "--eval_seed",
        type=int,
        default=None,
        help="evaluate on the episodes from this seed on (default: the task's, 1000 for robomimic, "
        "100000 for Push-T); the trained models are reused, the evaluations and report go to "
        "OUTPUT_DIR/eval_seedN and runs/RUN/eval_seedN",
    )
    parser.add_argument(
        "--n_episodes",
        type=int,
        default=None,
        help="evaluate on this many episodes instead of the budget's (50 robomimic_cpu, 100 cpu); with "
        "--eval_seed, e.g. 100 fresh episodes for a configuration chosen on the default ones; other "
        "counts go to their own eval_seedN_Mepisodes folders",
    )
    parser.add_argument(
        "--step_conditioning",
        choices=STEP_CONDITIONINGS,
        default=None,
        help="train SDP with this step encoder instead of the config's default (flatten, the paper's); "
        "the default output directory gets its name as a suffix",
    )
    parser.add_argument(
        "--sdp_flag",
        action="append",
        default=None,
        metavar="--policy.KEY=VALUE",
        help="train every SDP run with this policy flag, written --sdp_flag=--policy.KEY=VALUE (repeatable; "
        "it replaces the run's own value of KEY): a recipe carried from the screen to the comparison; "
        "needs --output_dir, so that the default folder keeps the default recipe",
    )
    parser.add_argument(
        "--curve_every",
        type=int,
        default=None,
        help="save a checkpoint every K steps, evaluate each on the same episodes (curves.png)",
    )


def resolve_budget(args: argparse.Namespace) -> tuple[str, Budget]:
    """The budget's name and settings, with --steps applied to every run (comparison and ablations)."""
    name = args.budget or ("robomimic_cpu" if args.env == "robomimic" else "cpu")
    budget = paper_budget() if name == "paper" else BUDGETS[name]
    if args.steps is None:
        return name, budget
    if args.steps < 1:
        raise SystemExit(f"--steps must be at least 1, got {args.steps}.")
    return f"{name}_{args.steps}steps", replace(budget, steps=args.steps, ablation_steps=args.steps)


def task_label(args: argparse.Namespace) -> str:
    return f"robomimic {args.task} (low-dim)" if args.env == "robomimic" else "Push-T keypoints"


@dataclass(frozen=True)
class Episodes:
    """The evaluation episodes: `n` from `seed` on, lerobot-eval's flags for them (the same for
    every run and sampler) and the evaluations' subfolder (`seed_dir`, see `run_dir`)."""

    seed: int
    n: int
    eval_args: list[str]
    seed_dir: str

    def __str__(self) -> str:
        return f"{self.n} episodes from seed {self.seed}"


def evaluation(args: argparse.Namespace, budget: Budget) -> Episodes:
    """The task's own episodes (no subfolder), or `--eval_seed`/`--n_episodes` others: their own
    `eval_seedN[_Mepisodes]` subfolder, so that an evaluation of other episodes is never reused."""
    default = ROBOMIMIC_EVAL_SEED if args.env == "robomimic" else EVAL_SEED
    seed = default if args.eval_seed is None else args.eval_seed
    if seed < 0:
        raise SystemExit(f"--eval_seed must be at least 0 (episode i starts from seed N + i), got {seed}.")
    n = budget.n_episodes if args.n_episodes is None else args.n_episodes
    if n < 1:
        raise SystemExit(f"--n_episodes must be at least 1, got {n}.")
    length = budget.episode_length
    if args.env == "robomimic":
        eval_args = robomimic_eval_args(args.task, n, args.device, length, seed)
    else:
        eval_args = pusht_eval_args(OBS_TYPE, n, seed, args.device, length)
    count = "" if n == budget.n_episodes else f"_{n}episodes"
    seed_dir = "" if (seed, count) == (default, "") else f"eval_seed{seed}{count}"
    return Episodes(seed, n, eval_args, seed_dir)


def training_data(args: argparse.Namespace, output_dir: Path) -> list[str]:
    """lerobot-train's dataset flags: --dataset_repo_id, else the task's own data (the Push-T zarr or
    the Hub; scripted robomimic demonstrations, recorded once into OUTPUT_DIR/data)."""
    if args.dataset_repo_id:
        root = [f"--dataset.root={args.dataset_root}"] if args.dataset_root else []
        return [f"--dataset.repo_id={args.dataset_repo_id}", *root]
    if args.env == "robomimic":
        from ..robomimic.job import dataset_args, record_demonstrations  # robosuite loads here

        return dataset_args(record_demonstrations(args.task, args.num_demos, output_dir / "data"))
    return keypoints_dataset_args(args.zarr, output_dir / "data")


def only(runs: list[Run], names: list[str] | None) -> list[Run]:
    """The runs named by --only (all when it is not given), in the run set's order, with the runs
    whose trained models they evaluate (`trains_as`): those train the model."""
    if names is None:
        return runs
    unknown = sorted(set(names) - {r.name for r in runs})
    if unknown:
        raise SystemExit(
            f"--only {' '.join(unknown)}: no such run in this run set; its runs are "
            f"{', '.join(r.name for r in runs)} (choose another with --runs)."
        )
    wanted = set(names) | {r.trains_as for r in runs if r.name in names}
    return [r for r in runs if r.name in wanted]


def default_output_dir(args: argparse.Namespace, budget_name: str) -> Path:
    """outputs/quality_[TASK_]BUDGET[_STEP_CONDITIONING]: one folder per comparison."""
    task = f"{args.task.lower()}_" if args.env == "robomimic" else ""
    conditioning = f"_{args.step_conditioning}" if args.step_conditioning else ""
    return Path("outputs") / f"quality_{task}{budget_name}{conditioning}"


def run(args: argparse.Namespace) -> dict:
    budget_name, budget = resolve_budget(args)
    for flag in ("jobs", "eval_jobs"):
        if getattr(args, flag) < 1:
            raise SystemExit(f"--{flag} must be at least 1, got {getattr(args, flag)}.")
    if args.sdp_flag and args.output_dir is None:
        raise SystemExit(
            "--sdp_flag changes how SDP trains: pass --output_dir, a folder of its own for those runs."
        )
    output_dir = args.output_dir or default_output_dir(args, budget_name)
    runs = {
        "comparison": comparison_runs,
        "horizon_control": horizon_control_runs,
        "ablations": ablation_runs,
        "warmstart": lambda b, d: warmstart_runs(b, d, dp_model(output_dir)),
    }
    if args.runs == "warmstart" and not dp_model(output_dir).exists() and not args.status:
        raise SystemExit(
            f"The warm-start runs start from the comparison's trained DP, and {dp_model(output_dir)} does "
            "not exist: run `--runs comparison` with this --output_dir first."
        )
    runs["screen"] = screen_runs  # shares dp and sdp_h2 with the comparison: not part of "all"
    kinds = [k for k in runs if k != "screen"] if args.runs == "all" else [args.runs]
    every_run = [r for kind in kinds for r in runs[kind](budget, args.device)]
    conditioned = with_step_conditioning(every_run, args.step_conditioning)
    selected = only(with_sdp_flags(conditioned, sdp_flags(args)), args.only)
    episodes = evaluation(args, budget)
    seed_dir = episodes.seed_dir
    print("\n".join(status(selected, output_dir, seed_dir)), flush=True)
    if args.status:
        return {}
    data_args = training_data(args, output_dir)
    common = [
        f"--batch_size={budget.batch_size}",
        "--seed=1000",
        "--num_workers=0",  # low-dimensional data, served from memory: every core to the update
        "--wandb.enable=false",
        # at most 2,000 steps lost to an interruption; curves evaluate the multiples of --curve_every
        f"--save_freq={math.gcd(args.curve_every or 0, max(1, min(budget.steps, 2000)))}",
        "--log_freq=200",
    ]
    report_dir = output_dir / seed_dir
    report_dir.mkdir(parents=True, exist_ok=True)
    results_file = report_dir / "results.json"
    # rows and sweeps of other run sets in this folder stay in the report
    previous = json.loads(results_file.read_text()) if results_file.exists() else {}
    rows = previous.get("rows", {})
    report = {"budget": budget_name, "settings": asdict(budget), "eval_seed": episodes.seed, "rows": rows}
    report["task"] = task_label(args)
    report |= {"sweep": previous["sweep"]} if "sweep" in previous else {}

    plan = Plan(
        output_dir,
        data_args,
        common,
        episodes.eval_args,
        seed_dir,
        args.curve_every,
        args.eval_jobs,
        args.jobs,
        args.precision,
    )
    for row in run_in_parallel(selected, lambda r: execute(r, plan, args.jobs == 1), args.jobs):
        rows[row["run"]] = row
        write_report(report, report_dir, budget)
        if args.curve_every:
            plot(
                rows,
                report_dir / "curves.png",
                f"{task_label(args)}, budget {budget_name}, {episodes} per point",
            )
        print("\n".join(status(selected, output_dir, seed_dir)), flush=True)
    if args.runs == "screen":
        report["probe"] = probe_screen(args, every_run, output_dir)
        write_report(report, report_dir, budget)
    if args.sweep:
        sweep = run_sweep(selected, plan)
        report["sweep"] = report.get("sweep", {}) | sweep
        write_report(report, report_dir, budget)
        title = f"{task_label(args)}, budget {budget_name}, {episodes}"
        cost_sweep.plot(report["sweep"], report_dir / "cost.png", title)
    print((report_dir / "results.md").read_text())
    return report


def write_report(report: dict, report_dir: Path, budget: Budget) -> None:
    """REPORT_DIR/results.json and its tables, results.md."""
    write_json(report_dir / "results.json", report)
    text = markdown(report["rows"], report["budget"], budget)
    text += sweep_markdown(report["sweep"]) if "sweep" in report else ""
    if report.get("probe"):
        text += "\n### Probe: the final models with true and shuffled observations\n\n"
        text += probe.markdown(report["probe"])
    (report_dir / "results.md").write_text(text)


def probe_screen(args: argparse.Namespace, runs: list[Run], output_dir: Path) -> dict:
    """The probe's report on every screen run trained so far, on the held-out data (empty, with a
    message, when there is none)."""
    if args.probe_dataset_root:
        root, repo_id = args.probe_dataset_root, args.probe_repo_id
    elif args.env == "robomimic":
        from ..robomimic.job import record_demonstrations  # robosuite loads here

        held_out = record_demonstrations(args.task, PROBE_DEMOS, output_dir / "probe_data", PROBE_DEMO_SEED)
        root, repo_id = Path(held_out["root"]), held_out["repo_id"]
    else:
        print("[probe] no held-out data: pass --probe_dataset_root to probe the screen's models", flush=True)
        return {}
    models = {}
    for run in runs:
        trained = model_root(output_dir, run) / "train"
        if trained_steps(trained) >= run.steps:
            models[run.name] = last_checkpoint(trained) / "pretrained_model"
    return probe.probe_models(models, root, repo_id, device=args.device) if models else {}


def run_in_parallel(runs: list[Run], execute_run: Callable[[Run], dict], jobs: int) -> Iterator[dict]:
    """Each run's row as it finishes, at most `jobs` runs at once. A run that evaluates another's
    model (`trains_as`) starts only once every training run is done, so no model is trained twice."""
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        for stage in ([r for r in runs if not r.trains_as], [r for r in runs if r.trains_as]):
            yield from (f.result() for f in as_completed([pool.submit(execute_run, r) for r in stage]))


def run_sweep(selected: list[Run], plan: Plan) -> dict[str, list[dict]]:
    """The comparison's final models at several samplers each (no retraining): every evaluation,
    `plan.eval_jobs` at once, then each model's points."""
    models = {}
    for run in selected:
        if run.name in ("dp", "sdp_h2", "sdp_h4"):
            policy_type = "diffusion" if run.name == "dp" else "sdp"
            model_dir = last_checkpoint(model_root(plan.output_dir, run) / "train") / "pretrained_model"
            models[run.name] = (policy_type, model_dir, run_dir(plan.output_dir, run, plan.seed_dir))
    evaluations = [e for m in models.values() for e in cost_sweep.evaluations(*m, plan.eval_args)]
    evaluate_all(evaluations, plan.eval_jobs)
    return {name: cost_sweep.points(*m) for name, m in models.items()}


def sweep_markdown(sweeps: dict[str, list[dict]]) -> str:
    out = ["", "### Quality against cost (the final models at several samplers)", ""]
    out += table(
        ["run", "sampler", "denoiser calls / chunk", "latency / chunk (ms)", "avg_max_reward", "pc_success"],
        [
            [
                name,
                p["sampler"],
                f"{p['denoiser_calls_per_chunk']:g}",
                f"{p['latency_per_chunk_ms']:.1f}",
                with_se(p, "avg_max_reward", 3),
                with_se(p, "pc_success", 1),
            ]
            for name, points in sweeps.items()
            for p in points
        ],
    )
    return "\n".join(out) + "\n"
