"""`lerobot-sdp-record-scripted`: scripted robomimic demonstrations recorded straight into a LeRobotDataset.

`--task Lift`, `PickPlaceCan` or `NutAssemblySquare` (the demonstrators are described in
`demonstrators.py`). Only successful episodes are kept (like robomimic's "proficient human" sets);
the success rate over all attempts is reported. Episode *i* is seeded `--seed + i`.
"""

import argparse
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..dataset_writing import without_datasets_progress_bars
from .dataset import create_dataset, dataset_features, make_frame
from .demonstrators import DEMONSTRATORS, GraspDemonstrator
from .env import RobomimicEnv
from .tasks import OBS_TYPES, get_task

# Seeds far from lerobot-eval's (which start at --seed, 1000 by default), so evaluation scenes are unseen.
DEFAULT_SEED = 100_000


class DemonstrationsFailedError(RuntimeError):
    """Fewer successful demonstrations than asked for within the allowed attempts."""


def default_repo_id(task: str) -> str:
    return f"local/scripted_{task.lower()}"


def record(
    num_episodes: int,
    output_dir: Path,
    task: str = "Lift",
    repo_id: str | None = None,
    obs_type: str = "low_dim",
    seed: int = DEFAULT_SEED,
    max_attempts: int | None = None,
    overwrite: bool = False,
    hold_steps: int = 0,
) -> dict:
    """Record `num_episodes` successful demonstrations; returns attempts, successes and success rate."""
    if num_episodes < 1:
        raise ValueError(f"--num_episodes must be at least 1, got {num_episodes}.")
    if hold_steps < 0:
        raise ValueError(f"--hold_steps must be 0 or more, got {hold_steps}.")
    if task not in DEMONSTRATORS:
        raise ValueError(f"No scripted demonstrator for {task!r}: use one of {sorted(DEMONSTRATORS)}.")
    max_attempts = max_attempts or 2 * num_episodes + 10
    spec = get_task(task)
    env = RobomimicEnv(task, obs_type=obs_type)
    dataset = create_dataset(
        repo_id or default_repo_id(task),
        output_dir,
        dataset_features(spec, obs_type, env.camera_names, env.image_size),
        overwrite,
    )
    demonstrator = DEMONSTRATORS[task](np.random.default_rng(seed))
    successes, attempts, lengths = 0, 0, []
    progress = tqdm(total=num_episodes, desc=f"Recording scripted {task}", unit="demo")
    try:
        with progress, without_datasets_progress_bars():
            while successes < num_episodes and attempts < max_attempts:
                frames = _run_episode(env, demonstrator, seed + attempts, spec.description, hold_steps)
                attempts += 1
                progress.set_postfix(attempts=attempts)
                if frames is None:
                    continue
                for frame in frames:
                    dataset.add_frame(frame)
                dataset.save_episode()
                successes += 1
                lengths.append(len(frames))
                progress.update()
    finally:
        dataset.finalize()
        env.close()
    stats = {
        "attempts": attempts,
        "successes": successes,
        "success_rate": successes / attempts,
        "mean_length": float(np.mean(lengths)) if lengths else 0.0,
    }
    if successes < num_episodes:
        raise DemonstrationsFailedError(
            f"Only {successes} of {num_episodes} demonstrations succeeded in {attempts} attempts ({stats}): "
            "raise --max_attempts."
        )
    return stats


def _run_episode(
    env: RobomimicEnv, demonstrator: GraspDemonstrator, seed: int, description: str, hold_steps: int = 0
) -> list[dict] | None:
    """One demonstration as LeRobot frames, or None if the task was not done within the horizon.

    The episode ends `hold_steps` steps after the first success (or at the horizon), the demonstrator
    still acting (lifting, or rising clear of the placed can): with `hold_steps=0` a Lift
    demonstration holds only the few frames of lift before the task's 4 cm threshold."""
    obs, _ = env.reset(seed=seed)
    demonstrator.reset(env.sim_env)
    frames, success_at = [], None
    while True:
        action = demonstrator.act(env.raw_observation)
        next_obs, reward, success, truncated, _ = env.step(action)
        if success and success_at is None:
            success_at = len(frames)
        ended = success_at is not None and (len(frames) - success_at >= hold_steps or truncated)
        frames.append(make_frame(obs, action, reward, ended, description))
        if ended:
            return frames
        if truncated:
            return None
        obs = next_obs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", choices=sorted(DEMONSTRATORS), default="Lift")
    parser.add_argument("--num_episodes", type=int, required=True, help="successful demonstrations to keep")
    parser.add_argument("--output_dir", type=Path, required=True, help="dataset root (--dataset.root)")
    parser.add_argument(
        "--repo_id", default=None, help="dataset id (--dataset.repo_id); default local/scripted_<task>"
    )
    parser.add_argument("--obs_type", choices=OBS_TYPES, default="low_dim")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="episode i uses seed + i")
    parser.add_argument(
        "--hold_steps",
        type=int,
        default=0,
        help="keep recording this many steps after success, the demonstrator still acting",
    )
    parser.add_argument("--max_attempts", type=int, default=None, help="give up after this many (2N+10)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing dataset at --output_dir"
    )
    args = parser.parse_args(argv)
    start = time.monotonic()
    stats = record(
        args.num_episodes,
        args.output_dir,
        args.task,
        args.repo_id,
        args.obs_type,
        args.seed,
        args.max_attempts,
        args.overwrite,
        args.hold_steps,
    )
    print(describe(args.task, stats, time.monotonic() - start, args.output_dir))


def describe(task: str, stats: dict, seconds: float, output_dir: Path) -> str:
    """The recorder's result line."""
    return (
        f"Scripted {task}: {stats['successes']}/{stats['attempts']} attempts succeeded "
        f"({100 * stats['success_rate']:.1f}%), mean length {stats['mean_length']:.1f} steps, "
        f"{seconds:.0f} s; kept {stats['successes']} demonstrations in {output_dir}."
    )


if __name__ == "__main__":
    main()
