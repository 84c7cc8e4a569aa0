"""`lerobot-sdp-record-lift`: a scripted Lift demonstrator recording straight into a LeRobotDataset.

No robomimic dataset is reachable from our machines, so this stands in for robomimic's Lift
demonstrations: reach above the cube, descend, close the gripper, lift; re-approach if the cube
slips. Each episode draws its own gains, offsets, heights, grasp time and action noise, so
demonstrations vary. Only successful episodes are kept (like robomimic's "proficient human" sets);
the success rate over all attempts is reported.
"""

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..dataset_writing import without_datasets_progress_bars
from .dataset import create_dataset, dataset_features, make_frame
from .env import RobomimicEnv
from .tasks import OBS_TYPES, get_task

# OSC_POSE maps an action of 1 to a 5 cm goal displacement (robosuite's output_max).
METERS_PER_ACTION = 0.05
OPEN, CLOSED = -1.0, 1.0
# Seeds far from lerobot-eval's (which start at --seed, 1000 by default), so evaluation scenes are unseen.
DEFAULT_SEED = 100_000


@dataclass
class LiftStyle:
    """One episode's randomised demonstrator parameters."""

    gain: float  # fraction of the remaining distance commanded per step
    hover: float  # height above the cube before descending (m)
    offset: np.ndarray  # grasp point offset from the cube centre (m)
    grasp_steps: int  # steps the gripper closes before lifting
    lift: float  # lift height above the cube's start (m)
    noise: float  # std of the Gaussian noise on position actions

    @classmethod
    def sample(cls, rng: np.random.Generator) -> "LiftStyle":
        return cls(
            gain=rng.uniform(0.5, 1.0),
            hover=rng.uniform(0.05, 0.12),
            offset=np.array([*rng.uniform(-0.006, 0.006, 2), rng.uniform(-0.012, 0.0)]),
            grasp_steps=int(rng.integers(6, 14)),
            lift=rng.uniform(0.10, 0.20),
            noise=rng.uniform(0.0, 0.1),
        )


class LiftDemonstrator:
    """Phase machine over robosuite's Lift observations: reach -> descend -> grasp -> lift."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.reset()

    def reset(self) -> None:
        self.style = LiftStyle.sample(self.rng)
        self.phase = "reach"
        self.phase_steps = 0
        self.cube_start_z: float | None = None

    def act(self, obs: dict) -> np.ndarray:
        """The 7-d OSC_POSE action for robosuite's raw observation dict (cube_pos, robot0_eef_pos)."""
        eef, cube = obs["robot0_eef_pos"], obs["cube_pos"]
        if self.cube_start_z is None:
            self.cube_start_z = float(cube[2])
        target, gripper = self._target(eef, cube)
        self.phase_steps += 1
        move = self.style.gain * (target - eef) / METERS_PER_ACTION + self.rng.normal(0, self.style.noise, 3)
        # No rotation: the gripper keeps its start orientation (fingers straddle the cube from above).
        return np.concatenate([np.clip(move, -1, 1), np.zeros(3), [gripper]])

    def _goto(self, phase: str) -> None:
        self.phase, self.phase_steps = phase, 0

    def _target(self, eef: np.ndarray, cube: np.ndarray) -> tuple[np.ndarray, float]:
        grasp_point = cube + self.style.offset
        above = grasp_point + np.array([0, 0, self.style.hover])
        if self.phase == "reach":
            if np.linalg.norm((above - eef)[:2]) < 0.01 and abs(above[2] - eef[2]) < 0.02:
                self._goto("descend")
            return above, OPEN
        if self.phase == "descend":
            if np.linalg.norm(grasp_point - eef) < 0.008 or self.phase_steps > 60:
                self._goto("grasp")
            return grasp_point, OPEN
        if self.phase == "grasp":
            if self.phase_steps >= self.style.grasp_steps:
                self._goto("lift")
            return grasp_point, CLOSED
        # lift: carry the cube up; if it slipped out of the fingers, open and start over.
        if np.linalg.norm(cube - eef) > 0.04:
            self._goto("reach")
            return eef, OPEN
        return np.array([eef[0], eef[1], self.cube_start_z + self.style.lift]), CLOSED


def record(
    num_episodes: int,
    output_dir: Path,
    repo_id: str = "local/scripted_lift",
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
    max_attempts = max_attempts or 2 * num_episodes + 10
    spec = get_task("Lift")
    env = RobomimicEnv("Lift", obs_type=obs_type)
    dataset = create_dataset(
        repo_id, output_dir, dataset_features(spec, obs_type, env.camera_names, env.image_size), overwrite
    )
    demonstrator = LiftDemonstrator(np.random.default_rng(seed))
    successes, attempts, lengths = 0, 0, []
    progress = tqdm(total=num_episodes, desc="Recording scripted Lift", unit="demo")
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
        raise RuntimeError(
            f"Only {successes} of {num_episodes} demonstrations succeeded in {attempts} attempts ({stats}): "
            "raise --max_attempts."
        )
    return stats


def _run_episode(
    env: RobomimicEnv, demonstrator: LiftDemonstrator, seed: int, task: str, hold_steps: int = 0
) -> list[dict] | None:
    """One demonstration as LeRobot frames, or None if the cube was not lifted in time.

    The episode ends `hold_steps` steps after the first success (or at the horizon), the demonstrator
    still lifting: with `hold_steps=0` a demonstration holds only the few frames of lift before the
    task's 4 cm threshold, while reaching and descending fill the rest."""
    obs, _ = env.reset(seed=seed)
    demonstrator.reset()
    frames, success_at = [], None
    while True:
        action = demonstrator.act(env.raw_observation)
        next_obs, reward, success, truncated, _ = env.step(action)
        if success and success_at is None:
            success_at = len(frames)
        ended = success_at is not None and (len(frames) - success_at >= hold_steps or truncated)
        frames.append(make_frame(obs, action, reward, ended, task))
        if ended:
            return frames
        if truncated:
            return None
        obs = next_obs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--num_episodes", type=int, required=True, help="successful demonstrations to keep")
    parser.add_argument("--output_dir", type=Path, required=True, help="dataset root (--dataset.root)")
    parser.add_argument("--repo_id", default="local/scripted_lift", help="dataset id (--dataset.repo_id)")
    parser.add_argument("--obs_type", choices=OBS_TYPES, default="low_dim")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="episode i uses seed + i")
    parser.add_argument(
        "--hold_steps",
        type=int,
        default=0,
        help="keep recording this many steps after success, still lifting",
    )
    parser.add_argument("--max_attempts", type=int, default=None, help="give up after this many (2N+10)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing dataset at --output_dir"
    )
    args = parser.parse_args(argv)
    stats = record(
        args.num_episodes,
        args.output_dir,
        args.repo_id,
        args.obs_type,
        args.seed,
        args.max_attempts,
        args.overwrite,
        args.hold_steps,
    )
    print(
        f"Scripted Lift: {stats['successes']}/{stats['attempts']} attempts succeeded "
        f"({100 * stats['success_rate']:.1f}%), mean length {stats['mean_length']:.1f} steps; "
        f"kept {stats['successes']} demonstrations in {args.output_dir}."
    )


if __name__ == "__main__":
    main()
