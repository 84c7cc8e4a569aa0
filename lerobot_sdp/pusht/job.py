"""The Push-T main job (`lerobot-sdp-pusht`, the README's first command).

1. data: convert the original Diffusion Policy zarr (--zarr, $SDP_PUSHT_ZARR, or ../shared/...) into a
   local keypoints LeRobotDataset; without a zarr, use Hub `lerobot/pusht_keypoints` when online;
2. train SDP with `lerobot-train --config_path=configs/pusht_state_cpu.json`;
3. evaluate with `lerobot-eval` on gym-pusht (batched sync envs);
4. print pc_success, avg_max_reward, the denoiser calls per chunk (counted) and where the videos are.

Stages that already finished are reused with --resume (an interrupted training run resumes from
its last checkpoint); an existing output directory is never overwritten without --overwrite.
"""

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from .benchmarks.stream_cost import stream_cost
from .lerobot_cli import CLIError, evaluate, pusht_eval_args, train
from .pusht_data import NoPushTDataError, keypoints_dataset_args

REPO = Path(__file__).resolve().parents[1]
OBS_TYPE = "environment_state_agent_pos"
EVAL_SEED = 100_000  # fixed episode seeds, shared with the quality benchmark


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output_dir", type=Path, default=Path("outputs/pusht_main"))
    p.add_argument("--config_path", type=Path, default=REPO / "configs" / "pusht_state_cpu.json")
    p.add_argument(
        "--zarr",
        type=Path,
        default=None,
        help="pusht_cchi_v7_replay.zarr (default: $SDP_PUSHT_ZARR, then ../shared/data/pusht/)",
    )
    p.add_argument("--eval_episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=None, help="override the config's training steps")
    p.add_argument("--device", default="cpu")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true", help="reuse finished stages, resume training")
    group.add_argument("--overwrite", action="store_true", help="delete --output_dir and start over")
    return p.parse_args(argv)


def prepare_output_dir(args: argparse.Namespace) -> None:
    if args.output_dir.exists() and any(args.output_dir.iterdir()):
        if args.overwrite:
            shutil.rmtree(args.output_dir)
        elif not args.resume:
            sys.exit(
                f"error: {args.output_dir} already exists. Pass --resume to reuse finished stages "
                "(and resume training), --overwrite to delete it, or another --output_dir."
            )
    args.output_dir.mkdir(parents=True, exist_ok=True)


def run_job(args: argparse.Namespace) -> dict:
    steps = args.steps or json.loads(args.config_path.read_text())["steps"]
    t0 = time.monotonic()
    train_args = [
        f"--config_path={args.config_path}",
        *keypoints_dataset_args(args.zarr, args.output_dir / "data"),
        f"--save_freq={min(steps, 1000)}",
        f"--policy.device={args.device}",
        "--job_name=sdp_pusht_main",
    ]
    logs = args.output_dir / "logs"
    model_dir = train(args.output_dir / "train", train_args, steps, logs / "train.log")
    t_train = time.monotonic() - t0
    eval_args = pusht_eval_args(OBS_TYPE, args.eval_episodes, EVAL_SEED, args.device)
    metrics = evaluate(model_dir, args.output_dir / "eval", eval_args, logs / "eval.log")
    config = json.loads((model_dir / "config.json").read_text())
    return {
        "pc_success": metrics["pc_success"],
        "avg_max_reward": metrics["avg_max_reward"],
        "avg_sum_reward": metrics["avg_sum_reward"],
        "n_episodes": metrics["n_episodes"],
        **stream_cost(model_dir),
        "num_inference_steps": config["num_inference_steps"] or config["num_train_timesteps"],
        "n_chunks": config["n_chunks"],
        "model_dir": str(model_dir),
        "videos": str(args.output_dir / "eval" / "videos"),
        "wall_time_s": round(time.monotonic() - t0, 1),
        "train_and_data_time_s": round(t_train, 1),
    }


def print_summary(summary: dict, output_dir: Path) -> None:
    print("\n=== SDP on Push-T (keypoints) ===")
    print(f"pc_success          {summary['pc_success']:.1f} %  over {summary['n_episodes']} episodes")
    print(f"avg_max_reward      {summary['avg_max_reward']:.3f}")
    print(
        f"denoiser calls      {summary['denoiser_calls_per_chunk']:g} per chunk (counted; N = "
        f"{summary['num_inference_steps']}, h = {summary['n_chunks']}; Diffusion Policy: N)"
    )
    print(f"videos              {summary['videos']}")
    print(f"summary             {output_dir / 'summary.json'}  ({summary['wall_time_s']:.0f} s in all)")


def main(argv=None) -> None:
    args = parse_args(argv)
    if not args.config_path.exists():
        sys.exit(f"error: config {args.config_path} not found; pass --config_path (see the repo's configs/).")
    prepare_output_dir(args)
    try:
        summary = run_job(args)
    except (CLIError, NoPushTDataError) as e:
        sys.exit(f"error: {e}")
    (args.output_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, args.output_dir)


if __name__ == "__main__":
    main()
