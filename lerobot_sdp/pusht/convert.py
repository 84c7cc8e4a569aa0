"""Convert Diffusion Policy's Push-T demonstrations (`pusht_cchi_v7_replay.zarr`) into a local
LeRobotDataset v3, so Push-T trains without the Hugging Face Hub.

    lerobot-sdp-convert-pusht ZARR OUT_DIR [--variant image|keypoints] [--episodes 0:10] ...

Variants:
- `image` (the default: a drop-in for Hub `lerobot/pusht`, which our users train on): exactly that
  dataset's schema: observation.image 96x96x3, observation.state = agent xy, action, next.reward,
  next.done, next.success, fps 10, one task. The one difference: images are stored as lossless PNG
  (dtype "image", ~1.4 kB a frame, ~36 MB in all) where the Hub stores lossy AV1 video; policies see
  the same keys, shapes and value range.
- `keypoints`: adds observation.environment_state, the 16 T-block keypoint coordinates of gym-pusht's
  `environment_state_agent_pos` observation, and by default drops the images, as Hub
  `lerobot/pusht_keypoints` does: state-only policies then never decode an image, which is what makes
  CPU training fast (`--with-images` keeps them).

Keypoints, reward and success come from gym-pusht's own code (`PushTEnv.get_obs`, `_get_coverage`,
the reward of `PushTEnv.step`), evaluated on the recorded block pose, so training observations are the
ones `lerobot-eval` sees. Every state, action and (PNG) image value is copied unchanged and checked
after the write by reloading the dataset.
"""

import argparse
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm import tqdm

from ..dataset_writing import clear_output_dir, without_datasets_progress_bars

with warnings.catch_warnings():
    # pygame, imported by gym-pusht, warns that pkg_resources is deprecated: noise for our users.
    warnings.filterwarnings("ignore", "pkg_resources is deprecated", UserWarning)
    from gym_pusht.envs.pusht import PushTEnv

VARIANTS = ("image", "keypoints")
DEFAULT_VARIANT = "image"
DEFAULT_REPO_IDS = {"image": "local/pusht", "keypoints": "local/pusht_keypoints"}
# Hub lerobot/pusht's fps and its one task string.
FPS = 10
PUSHT_TASK = "Push the T-shaped block onto the T-shaped target."
IMAGE_SHAPE = (96, 96, 3)
# No video is written or read, but naming a backend skips LeRobot's torchcodec probe, which prints a
# long traceback on machines without FFmpeg's shared libraries.
VIDEO_BACKEND = "pyav"
# Shape of one frame of each zarr array.
ZARR_SHAPES = {
    "data/state": (5,),  # agent x, agent y, block x, block y, block angle
    "data/action": (2,),
    "data/img": IMAGE_SHAPE,
}


class ConversionError(Exception):
    """Bad input or a failed check, reported to the user as one line naming the problem and the fix."""


@dataclass(frozen=True)
class PushTZarr:
    """The arrays of a Diffusion Policy Push-T replay zarr, checked for shape and consistency.

    `img` stays a lazy zarr array (the full float32 array is 2.8 GB); the rest is in memory.
    """

    state: np.ndarray
    action: np.ndarray
    img: zarr.Array | None
    episode_ends: np.ndarray

    @property
    def num_episodes(self) -> int:
        return len(self.episode_ends)

    def frames(self, episode: int) -> slice:
        start = 0 if episode == 0 else int(self.episode_ends[episode - 1])
        return slice(start, int(self.episode_ends[episode]))

    def length(self, episode: int) -> int:
        return self.frames(episode).stop - self.frames(episode).start

    def images(self, episode: int) -> np.ndarray:
        """One episode's images as uint8, refusing any value a uint8 PNG would not store exactly."""
        img = self.img[self.frames(episode)]
        if not np.array_equal(img, np.clip(np.round(img), 0, 255)):
            raise ConversionError(
                f"data/img of episode {episode} holds values that are not integers in 0..255, so they "
                "cannot be stored losslessly; check the zarr, or convert with --variant keypoints"
            )
        return img.astype(np.uint8)


def open_pusht_zarr(path: Path, with_images: bool) -> PushTZarr:
    """Open and validate the zarr at `path` (data/{state,action,img}, meta/episode_ends)."""
    if not path.exists():
        raise ConversionError(f"{path} does not exist; pass the path of pusht_cchi_v7_replay.zarr")
    try:
        group = zarr.open_group(str(path), mode="r")
    except (FileNotFoundError, ValueError) as err:
        raise ConversionError(f"{path} is not a zarr group ({err}); pass pusht_cchi_v7_replay.zarr") from None
    names = [name for name in ZARR_SHAPES if with_images or name != "data/img"] + ["meta/episode_ends"]
    missing = [name for name in names if name not in group]
    if missing:
        raise ConversionError(
            f"{path} lacks {', '.join(missing)}; expected Diffusion Policy's Push-T layout "
            "(data/state, data/action, data/img, meta/episode_ends)"
        )
    num_frames = group["data/state"].shape[0]
    for name in names[:-1]:
        expected = (num_frames, *ZARR_SHAPES[name])
        if group[name].shape != expected:
            raise ConversionError(
                f"{path}/{name} has shape {group[name].shape}, expected {expected} "
                f"(one row per frame of data/state); the arrays are inconsistent, re-export the zarr"
            )
    ends = np.asarray(group["meta/episode_ends"][:])
    _check_episode_ends(ends, num_frames, path)
    return PushTZarr(
        state=np.asarray(group["data/state"][:]),
        action=np.asarray(group["data/action"][:]),
        img=group["data/img"] if with_images else None,
        episode_ends=ends,
    )


def _check_episode_ends(ends: np.ndarray, num_frames: int, path: Path) -> None:
    """meta/episode_ends must be the exclusive end index of each episode, the last one the frame count."""
    problem = None
    if ends.ndim != 1 or len(ends) == 0:
        problem = f"has shape {ends.shape}, expected one end index per episode"
    elif np.any(np.diff(ends) <= 0) or ends[0] <= 0:
        problem = "is not strictly increasing from a positive first end (an episode would be empty)"
    elif ends[-1] != num_frames:
        problem = f"ends at frame {ends[-1]} but data/state has {num_frames} frames"
    if problem:
        raise ConversionError(f"{path}/meta/episode_ends {problem}; the zarr is inconsistent, re-export it")


def parse_episodes(spec: str, num_episodes: int) -> list[int]:
    """`--episodes` syntax: a Python slice `START:STOP` (either end may be left out) or a comma list."""
    try:
        if ":" in spec:
            start, stop = (int(part) if part else None for part in spec.split(":"))
            episodes = list(range(num_episodes))[slice(start, stop)]
        else:
            episodes = [int(part) for part in spec.split(",")]
    except ValueError:
        raise ConversionError(f"--episodes {spec!r} is not START:STOP or a comma list like 0,3,7") from None
    return check_episodes(episodes, num_episodes)


def check_episodes(episodes: Sequence[int], num_episodes: int) -> list[int]:
    """The selected episode indices as a list, refusing an empty, out-of-range or repeating selection."""
    episodes = list(episodes)
    if not episodes:
        raise ConversionError(f"the episode selection is empty; the zarr has episodes 0..{num_episodes - 1}")
    outside = [ep for ep in episodes if not 0 <= ep < num_episodes]
    if outside:
        raise ConversionError(f"episodes {outside} do not exist; the zarr has episodes 0..{num_episodes - 1}")
    if len(set(episodes)) != len(episodes):
        raise ConversionError(f"episodes {episodes} repeat an episode; select each episode once")
    return episodes


class BlockGeometry:
    """gym-pusht's T-block geometry, through a live `PushTEnv`: keypoints exactly as the
    `environment_state_agent_pos` observation reports them, coverage exactly as the env's reward uses it."""

    def __init__(self):
        self._env = PushTEnv(obs_type="environment_state_agent_pos")
        self._env.reset(seed=0)  # builds the pymunk space, the block and the goal pose
        self.success_threshold = self._env.success_threshold

    def place_block(self, x: float, y: float, angle: float) -> None:
        """Put the block at the pose the zarr recorded: its body origin at (x, y), rotated by `angle`.

        Angle first, then position: pymunk rotates a body about its centre of gravity, so this order
        leaves the origin exactly at (x, y). gym-pusht's `reset_to_state` uses the opposite order (its
        docstring's legacy warning) and would shift the recorded block by up to ~90 px. No physics step
        is taken, so the agent cannot push the block away.
        """
        self._env.block.angle = angle
        self._env.block.position = (x, y)

    def observe(self, block_pose: np.ndarray) -> tuple[np.ndarray, float]:
        """Keypoints (16,) float32 and goal coverage for one recorded (x, y, angle) block pose."""
        self.place_block(*(float(v) for v in block_pose))
        keypoints = self._env.get_obs()["environment_state"].astype(np.float32)
        return keypoints, self._env._get_coverage()


def next_step_labels(coverage: np.ndarray, success_threshold: float) -> dict[str, np.ndarray]:
    """next.reward / next.success / next.done of one episode, from each frame's goal coverage.

    Reward and success are `PushTEnv.step`'s: clip(coverage / 0.95, 0, 1) and coverage > 0.95. LeRobot's
    `next.*` describe the state after frame t's action, i.e. frame t+1; the zarr has no state after its
    last frame, so that frame repeats its own (as the converter that built Hub lerobot/pusht did). done
    is true on the last frame only; that converter also shifted its done flag and so marked the last
    two frames, an artefact not kept here.
    """
    next_coverage = np.append(coverage[1:], coverage[-1])
    done = np.zeros(len(coverage), dtype=bool)
    done[-1] = True
    return {
        "next.reward": np.clip(next_coverage / success_threshold, 0.0, 1.0).astype(np.float32),
        "next.success": next_coverage > success_threshold,
        "next.done": done,
    }


def pusht_features(variant: str, with_images: bool) -> dict[str, dict]:
    """LeRobot feature spec: Hub lerobot/pusht's (names included), plus keypoints for that variant."""
    motors = {"motors": ["motor_0", "motor_1"]}
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": motors},
        "action": {"dtype": "float32", "shape": (2,), "names": motors},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    if with_images:
        features["observation.image"] = {
            "dtype": "image",
            "shape": IMAGE_SHAPE,
            "names": ["height", "width", "channel"],
        }
    if variant == "keypoints":
        features["observation.environment_state"] = {
            "dtype": "float32",
            "shape": (16,),
            "names": {"motors": [f"motor_{i}" for i in range(16)]},  # Hub lerobot/pusht_keypoints' names
        }
    return features


def episode_columns(
    data: PushTZarr, episode: int, geometry: BlockGeometry, variant: str, with_images: bool
) -> dict[str, np.ndarray]:
    """All feature values of one zarr episode, one row per frame."""
    frames = data.frames(episode)
    state = data.state[frames]
    keypoints, coverage = zip(*(geometry.observe(pose) for pose in state[:, 2:5]), strict=True)
    columns = {
        "observation.state": state[:, :2],
        "action": data.action[frames],
        **next_step_labels(np.array(coverage), geometry.success_threshold),
    }
    if variant == "keypoints":
        columns["observation.environment_state"] = np.stack(keypoints)
    if with_images:
        columns["observation.image"] = data.images(episode)
    return columns


def convert_pusht(
    zarr_path: str | Path,
    out_dir: str | Path,
    variant: str = DEFAULT_VARIANT,
    episodes: Sequence[int] | str | None = None,
    with_images: bool | None = None,
    repo_id: str | None = None,
    overwrite: bool = False,
    verify: bool = True,
) -> Path:
    """Write the zarr's `episodes` (default: all) as a LeRobotDataset at `out_dir` and return `out_dir`.

    episodes: zarr episode indices, or a string as `--episodes` takes (`0:10`, `0,3,7`); output episodes
    are numbered 0..len(episodes)-1 in the order given.
    with_images: None means the variant's Hub default (image: yes, keypoints: no).
    verify: reload the dataset and check it against the zarr (`verify_conversion`).
    A failed conversion or verification leaves no `out_dir` behind.
    """
    if variant not in VARIANTS:
        raise ConversionError(f"unknown variant {variant!r}; use one of {', '.join(VARIANTS)}")
    with_images = variant == "image" if with_images is None else with_images
    if variant == "image" and not with_images:
        raise ConversionError("the image variant always stores images; use --variant keypoints (no images)")
    zarr_path, out_dir = Path(zarr_path), Path(out_dir)
    repo_id = repo_id or DEFAULT_REPO_IDS[variant]
    data = open_pusht_zarr(zarr_path, with_images)
    if episodes is None:
        episodes = range(data.num_episodes)
    elif isinstance(episodes, str):
        episodes = parse_episodes(episodes, data.num_episodes)
    episodes = check_episodes(episodes, data.num_episodes)
    try:
        clear_output_dir(out_dir, overwrite)
    except FileExistsError as err:
        raise ConversionError(str(err)) from None
    try:
        _write_dataset(data, out_dir, repo_id, variant, episodes, with_images)
        if verify:
            verify_conversion(data, out_dir, repo_id, variant, episodes, with_images)
    except BaseException:
        shutil.rmtree(out_dir, ignore_errors=True)
        raise
    return out_dir


def _write_dataset(
    data: PushTZarr, out_dir: Path, repo_id: str, variant: str, episodes: list[int], with_images: bool
) -> None:
    """Create the dataset with LeRobot's own writer: one add_frame per frame, one save_episode per episode."""
    dataset = LeRobotDataset.create(
        repo_id=repo_id,
        fps=FPS,
        features=pusht_features(variant, with_images),
        root=out_dir,
        use_videos=False,
        video_backend=VIDEO_BACKEND,
    )
    geometry = BlockGeometry()
    desc = f"Push-T {variant} -> {out_dir.name}"
    progress = tqdm(total=sum(map(data.length, episodes)), unit="frame", desc=desc)
    with progress, without_datasets_progress_bars():
        for episode in episodes:
            columns = episode_columns(data, episode, geometry, variant, with_images)
            for t in range(len(columns["action"])):
                # LeRobot's features of shape (1,) take 1-element arrays, hence the [t : t + 1] slices.
                frame = {k: v[t : t + 1] if v.ndim == 1 else v[t] for k, v in columns.items()}
                dataset.add_frame({**frame, "task": PUSHT_TASK})
            dataset.save_episode()
            progress.update(len(columns["action"]))
    dataset.finalize()


def verify_conversion(
    data: PushTZarr, out_dir: Path, repo_id: str, variant: str, episodes: list[int], with_images: bool
) -> None:
    """Reload `out_dir` with LeRobotDataset and check it against the zarr: episode and frame counts,
    episode lengths and order, the task, and every stored value bit for bit: state, action and image
    as in the zarr, keypoints and next.* as recomputed."""
    dataset = LeRobotDataset(repo_id, root=out_dir, video_backend=VIDEO_BACKEND)
    lengths = [data.length(ep) for ep in episodes]
    _expect(dataset.meta.total_episodes == len(episodes), f"{dataset.meta.total_episodes} episodes saved")
    _expect(dataset.meta.total_frames == sum(lengths), f"{dataset.meta.total_frames} frames saved")
    _expect(list(dataset.meta.tasks.index) == [PUSHT_TASK], f"tasks {list(dataset.meta.tasks.index)}")
    table = dataset.hf_dataset.with_format("numpy")
    geometry = BlockGeometry()
    starts = np.cumsum([0, *lengths]).tolist()
    for new_index, episode in enumerate(episodes):
        rows = table[starts[new_index] : starts[new_index + 1]]
        _expect(np.all(rows["episode_index"] == new_index), f"episode {episode} is split or mislabelled")
        frames_in_order = np.array_equal(rows["frame_index"], np.arange(lengths[new_index]))
        _expect(frames_in_order, f"frame order of episode {episode}")
        expected = episode_columns(data, episode, geometry, variant, with_images)
        for key, value in expected.items():
            _expect(np.array_equal(rows[key], value), f"{key} of episode {episode}")


def _expect(ok: bool, what: str) -> None:
    if not ok:
        raise ConversionError(f"verification failed: {what} does not match the zarr; please report this")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="lerobot-sdp-convert-pusht",
        description="Convert pusht_cchi_v7_replay.zarr (Diffusion Policy's Push-T demonstrations) into a "
        "local LeRobotDataset v3. Load it with --dataset.repo_id=REPO_ID --dataset.root=OUT_DIR.",
    )
    parser.add_argument("zarr", type=Path, help="path of pusht_cchi_v7_replay.zarr")
    parser.add_argument("out_dir", type=Path, help="dataset directory to create")
    parser.add_argument(
        "--variant",
        choices=VARIANTS,
        default=DEFAULT_VARIANT,
        help="image: Hub lerobot/pusht's schema (default); keypoints: adds observation.environment_state "
        "and, like Hub lerobot/pusht_keypoints, stores no images",
    )
    parser.add_argument("--repo-id", help="dataset repo_id (default: local/pusht or local/pusht_keypoints)")
    parser.add_argument("--episodes", help="episode subset: START:STOP (e.g. 0:10) or a list (0,3,7)")
    parser.add_argument("--with-images", action="store_true", default=None, help="keypoints: store images")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset at OUT_DIR")
    parser.add_argument("--no-verify", dest="verify", action="store_false", help="skip reload-and-compare")
    args = parser.parse_args(argv)
    try:
        out_dir = convert_pusht(
            args.zarr,
            args.out_dir,
            variant=args.variant,
            episodes=args.episodes,
            with_images=args.with_images,
            repo_id=args.repo_id,
            overwrite=args.overwrite,
            verify=args.verify,
        )
    # OSError: an unwritable or full OUT_DIR, a zarr that cannot be read; its message names the path.
    except (ConversionError, OSError) as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    repo_id = args.repo_id or DEFAULT_REPO_IDS[args.variant]
    checked = "verified against the zarr" if args.verify else "not verified"
    print(f"Wrote {out_dir} ({checked}). Train with --dataset.repo_id={repo_id} --dataset.root={out_dir}")
