"""`lerobot-sdp-convert-robomimic`: robomimic hdf5 demonstrations -> a local LeRobotDataset.

Nothing lost: after writing, the dataset is read back and must hold the same number of episodes and
frames as the source, with every state, object-state, image, action, reward and done equal (floats
compared after the cast to the dataset's float32).
"""

import argparse
import logging
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from lerobot.utils.utils import init_logging
from tqdm import tqdm

from ..dataset_writing import without_datasets_progress_bars
from .dataset import DONE, REWARD, create_dataset, dataset_features, make_frame
from .hdf5 import Demo, demo_names, open_robomimic, read_demo, task_of
from .tasks import OBS_TYPES, TaskSpec

logger = logging.getLogger(__name__)


def convert(
    hdf5_path: Path,
    output_dir: Path,
    repo_id: str,
    obs_type: str = "low_dim",
    task: str | None = None,
    camera_names: list[str] | None = None,
    filter_key: str | None = None,
    overwrite: bool = False,
) -> LeRobotDataset:
    """Convert, then verify; returns the dataset as read back from `output_dir`."""
    hdf5_path = Path(hdf5_path)
    if not hdf5_path.is_file():
        raise FileNotFoundError(f"No robomimic file at {hdf5_path}.")
    with open_robomimic(hdf5_path) as f:
        spec = task_of(f, task)
        cameras = list(camera_names or spec.cameras)
        names = demo_names(f, filter_key)
        image_size = _image_size(f, names[0], cameras) if obs_type == "image" else spec.image_size
        features = dataset_features(spec, obs_type, cameras, image_size)
        dataset = create_dataset(repo_id, output_dir, features, overwrite)
        lengths = []
        with without_datasets_progress_bars():
            for name in tqdm(names, desc=f"Converting {hdf5_path.name}", unit="demo"):
                demo = read_demo(f, name, spec, obs_type, cameras)
                _write_episode(dataset, demo, spec)
                lengths.append(len(demo))
        dataset.finalize()
        converted = LeRobotDataset(repo_id, root=output_dir)
        _verify_counts(converted, lengths)
        # Raw column values (numpy, decoded images), not LeRobot's torch transform (float CHW images).
        table = converted.hf_dataset.with_format("numpy")
        starts = np.cumsum([0, *lengths[:-1]])
        # Read each demo from the file again rather than keep them all: image demos run to gigabytes.
        for episode, name in enumerate(tqdm(names, desc="Verifying", unit="demo")):
            demo = read_demo(f, name, spec, obs_type, cameras)
            _verify_episode(table, demo, episode, int(starts[episode]))
    logger.info("Converted %d demonstrations (%d frames) to %s.", len(lengths), sum(lengths), output_dir)
    return converted


def _image_size(f, name: str, cameras: list[str]) -> int:
    """The square image size stored in the file (robomimic renders 84 px; 240 px for Tool-hang)."""
    sizes = {
        cam: f["data"][name]["obs"][f"{cam}_image"].shape[1:3]
        for cam in cameras
        if f"{cam}_image" in f["data"][name]["obs"]
    }
    if len(sizes) != len(cameras):
        available = sorted(key[: -len("_image")] for key in f["data"][name]["obs"] if key.endswith("_image"))
        raise KeyError(f"{name} lacks cameras {sorted(set(cameras) - set(sizes))}; it has {available}.")
    if len({tuple(s) for s in sizes.values()}) != 1 or any(h != w for h, w in sizes.values()):
        raise ValueError(f"Images must be square and of one size across cameras, got {sizes}.")
    return int(next(iter(sizes.values()))[0])


def _write_episode(dataset: LeRobotDataset, demo: Demo, spec: TaskSpec) -> None:
    if len(demo) == 0:
        raise ValueError(
            f"{demo.name} is empty: remove it from the file (or filter it out with --filter_key)."
        )
    for t in range(len(demo)):
        obs = {key: value[t] for key, value in demo.obs.items() if key != "pixels"}
        obs["pixels"] = {cam: images[t] for cam, images in demo.obs.get("pixels", {}).items()}
        dataset.add_frame(make_frame(obs, demo.actions[t], demo.rewards[t], demo.dones[t], spec.description))
    dataset.save_episode()


def _verify_counts(dataset: LeRobotDataset, lengths: list[int]) -> None:
    if dataset.meta.total_episodes != len(lengths) or dataset.meta.total_frames != sum(lengths):
        raise RuntimeError(
            f"Conversion lost data: the source has {len(lengths)} demos / {sum(lengths)} frames, the dataset "
            f"{dataset.meta.total_episodes} episodes / {dataset.meta.total_frames} frames."
        )


def _verify_episode(table, demo: Demo, episode: int, start: int) -> None:
    """Every value of one demonstration equals its converted episode (rows `start`... of `table`)."""
    rows = table[start : start + len(demo)]
    if set(rows["episode_index"]) != {episode}:
        raise RuntimeError(f"{demo.name}: frames {start}..{start + len(demo)} are not all episode {episode}.")
    expected = {
        OBS_STATE: demo.obs["agent_pos"].astype(np.float32),
        ACTION: demo.actions.astype(np.float32),
        REWARD: demo.rewards.astype(np.float32).reshape(-1, 1),
        DONE: demo.dones.astype(bool).reshape(-1, 1),
    }
    if "environment_state" in demo.obs:
        expected[OBS_ENV_STATE] = demo.obs["environment_state"].astype(np.float32)
    for cam, images in demo.obs.get("pixels", {}).items():
        expected[f"{OBS_IMAGES}.{cam}"] = images
    for key, want in expected.items():
        got = np.stack([np.asarray(value) for value in rows[key]]).reshape(want.shape)
        if not np.array_equal(got, want):
            raise RuntimeError(
                f"Conversion changed {demo.name} {key}: "
                f"{int((got != want).sum())} of {want.size} values differ."
            )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--hdf5", type=Path, required=True, help="robomimic file, e.g. lift/ph/low_dim_v141.hdf5"
    )
    parser.add_argument("--output_dir", type=Path, required=True, help="dataset root (--dataset.root)")
    parser.add_argument(
        "--repo_id", default=None, help="dataset id (--dataset.repo_id); default local/<file stem>"
    )
    parser.add_argument("--obs_type", choices=OBS_TYPES, default="low_dim")
    parser.add_argument("--task", default=None, help="override the task named in the file's env_args")
    parser.add_argument(
        "--camera_names", default=None, help="comma-separated cameras (image); default the task's"
    )
    parser.add_argument("--filter_key", default=None, help="convert only mask/<filter_key>, e.g. train")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing dataset at --output_dir"
    )
    args = parser.parse_args(argv)
    init_logging()
    cameras = [c.strip() for c in args.camera_names.split(",") if c.strip()] if args.camera_names else None
    dataset = convert(
        args.hdf5,
        args.output_dir,
        args.repo_id or f"local/{args.hdf5.stem}",
        obs_type=args.obs_type,
        task=args.task,
        camera_names=cameras,
        filter_key=args.filter_key,
        overwrite=args.overwrite,
    )
    print(
        f"Wrote {dataset.meta.total_episodes} episodes ({dataset.meta.total_frames} frames) "
        f"to {args.output_dir}, "
        "verified equal to the source."
    )


if __name__ == "__main__":
    main()
