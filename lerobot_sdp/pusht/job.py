"""The Push-T main job (`lerobot-sdp-pusht`, the README's first command).

1. data: convert the original Diffusion Policy zarr (--zarr, $SDP_PUSHT_ZARR, or ../shared/...) into a
   local keypoints LeRobotDataset; without a zarr, use Hub `lerobot/pusht_keypoints` when online;
2. train SDP with `lerobot-train --config_path=configs/pusht_state_cpu.json`;
3. evaluate with `lerobot-eval` on gym-pusht (batched sync envs);
4. print pc_success, avg_max_reward, the denoiser calls and latency per chunk, the checkpoint and
   where lerobot-eval wrote the rollout videos; OUTPUT_DIR/summary.json has all of it.

Stages that already finished are reused with --resume; see `lerobot_sdp.main_job`.
"""

import argparse
from pathlib import Path

from ..main_job import StageTimings, job_parser, run_main, train_evaluate_measure
from .data import NoPushTDataError, converted, keypoints_dataset_args
from .evaluation import EVAL_SEED, OBS_TYPE, pusht_eval_args


def parse_args(argv=None) -> argparse.Namespace:
    p = job_parser(__doc__, "outputs/pusht_main", "pusht_state_cpu")
    p.add_argument(
        "--zarr",
        type=Path,
        default=None,
        help="pusht_cchi_v7_replay.zarr (default: $SDP_PUSHT_ZARR, then ../shared/data/pusht/)",
    )
    return p.parse_args(argv)


def run_job(args: argparse.Namespace, timings: StageTimings) -> dict:
    data_dir = args.output_dir / "data"
    with timings.stage("data", reused=converted(data_dir)):
        dataset_args = keypoints_dataset_args(args.zarr, data_dir)
    eval_args = pusht_eval_args(OBS_TYPE, args.eval_episodes, EVAL_SEED, args.device)
    return train_evaluate_measure(args, timings, dataset_args, eval_args, "sdp_pusht_main")


def main(argv=None) -> None:
    run_main(parse_args(argv), run_job, "SDP on Push-T (keypoints)", (NoPushTDataError,))


if __name__ == "__main__":
    main()
