"""The robomimic main job (`lerobot-sdp-robomimic`): scripted demonstrations to an evaluated SDP policy.

1. data: record --num_demos successful scripted demonstrations of --task (default PickPlaceCan, low-dim
   observations) into a local LeRobotDataset; the demonstrator's own success rate is kept;
2. train SDP with `lerobot-train --config_path=configs/robomimic_<task>_lowdim_cpu.json`;
3. evaluate with `lerobot-eval --env.type=robomimic` on --eval_episodes episodes from seed 1000 on
   (the demonstrations use seeds from 100000 on, so every evaluation scene is unseen);
4. print pc_success, the denoiser calls and latency per chunk, the checkpoint and where lerobot-eval
   wrote the rollout videos; OUTPUT_DIR/summary.json has all of it.

Stages that already finished are reused with --resume; see `lerobot_sdp.main_job`.
"""

import argparse
import json
import time
from pathlib import Path

from .. import shipped_configs
from ..main_job import StageTimings, job_parser, run_main, train_evaluate_measure
from .evaluation import robomimic_eval_args
from .record_scripted import DEFAULT_SEED, DemonstrationsFailedError, default_repo_id, describe, record

# The shipped config of each task with a scripted demonstrator.
CONFIGS = {"Lift": "robomimic_lift_lowdim_cpu", "PickPlaceCan": "robomimic_can_lowdim_cpu"}
RECORDING = "recording.json"  # the demonstrator's statistics, beside the dataset


def parse_args(argv=None) -> argparse.Namespace:
    # fp32 by default: on Can, bf16 training measured 8 +- 4.8 points below it (docs/robomimic.md)
    p = job_parser(__doc__, "outputs/robomimic_main", None, precision="fp32")
    p.add_argument("--task", choices=sorted(CONFIGS), default="PickPlaceCan")
    p.add_argument("--num_demos", type=int, default=200, help="successful demonstrations to record")
    p.add_argument("--demo_seed", type=int, default=DEFAULT_SEED, help="demonstration i uses demo_seed + i")
    args = p.parse_args(argv)
    if args.num_demos < 1:
        p.error(f"--num_demos must be at least 1, got {args.num_demos}")
    if args.config_path is None:
        args.config_path = shipped_configs.path(CONFIGS[args.task])
    return args


def recorded(data_dir: Path) -> dict | None:
    """The recording statistics of a finished data stage (None when there is none)."""
    path = data_dir / RECORDING
    return json.loads(path.read_text()) if path.exists() else None


def record_demonstrations(task: str, num_demos: int, data_dir: Path, demo_seed: int = DEFAULT_SEED) -> dict:
    """Record the demonstrations into DATA_DIR/demos (or reuse a finished recording); their
    statistics, with the dataset's `repo_id` and `root`."""
    root = data_dir / "demos"
    stats = recorded(data_dir)
    if stats is not None:
        print(f"[data] reusing {root} ({stats['successes']} demonstrations)", flush=True)
    else:
        print(f"[data] recording {num_demos} scripted {task} demonstrations -> {root}", flush=True)
        # A recording cut short leaves a partial dataset and no statistics: it is recorded again.
        start = time.monotonic()
        stats = record(num_demos, root, task, seed=demo_seed, overwrite=True)
        stats |= {"repo_id": default_repo_id(task), "seconds": round(time.monotonic() - start, 1)}
        print(f"[data] {describe(task, stats, stats['seconds'], root)}", flush=True)
        (data_dir / RECORDING).write_text(json.dumps(stats, indent=2))
    # derived, not stored: an output folder copied or moved since trains on its own demonstrations
    return stats | {"root": str(root)}


def dataset_args(stats: dict) -> list[str]:
    """lerobot-train's dataset flags for a recording."""
    return [f"--dataset.repo_id={stats['repo_id']}", f"--dataset.root={stats['root']}"]


def run_job(args: argparse.Namespace, timings: StageTimings) -> dict:
    data_dir = args.output_dir / "data"
    with timings.stage("data", reused=recorded(data_dir) is not None):
        stats = record_demonstrations(args.task, args.num_demos, data_dir, args.demo_seed)
    eval_args = robomimic_eval_args(args.task, args.eval_episodes, args.device)
    summary = train_evaluate_measure(args, timings, dataset_args(stats), eval_args, "sdp_robomimic_main")
    return {"task": args.task, "demonstrations": stats, **summary}


def main(argv=None) -> None:
    args = parse_args(argv)
    run_main(
        args,
        run_job,
        f"SDP on robomimic {args.task} (low-dim, scripted demonstrations)",
        (DemonstrationsFailedError,),
    )


if __name__ == "__main__":
    main()
