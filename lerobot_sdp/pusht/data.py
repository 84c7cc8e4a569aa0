"""Where Push-T training data comes from: the original Diffusion Policy zarr (converted once into a
local LeRobotDataset) when one is given or found, else the Hugging Face Hub when online."""

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SHARED_ZARR = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
HUB_KEYPOINTS = "lerobot/pusht_keypoints"


class NoPushTDataError(RuntimeError):
    pass


def find_zarr(explicit: Path | None) -> Path | None:
    """--zarr, then $SDP_PUSHT_ZARR, then ../shared/data/pusht/ beside the repo."""
    env = os.environ.get("SDP_PUSHT_ZARR")
    for path, origin in ((explicit, "--zarr"), (Path(env) if env else None, "SDP_PUSHT_ZARR")):
        if path is not None:
            if not path.exists():
                raise NoPushTDataError(f"{origin} points at {path}, which does not exist.")
            return path
    return SHARED_ZARR if SHARED_ZARR.exists() else None


def hub_offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "0").lower() in ("1", "true", "yes", "on")


def keypoints_root(data_dir: Path) -> Path:
    """Where `keypoints_dataset_args` converts the zarr to."""
    return data_dir / "pusht_keypoints"


def converted(data_dir: Path) -> bool:
    """Whether a finished conversion sits in data_dir (it is reused then)."""
    return (keypoints_root(data_dir) / "meta" / "info.json").exists()


def keypoints_dataset_args(zarr: Path | None, data_dir: Path) -> list[str]:
    """lerobot-train's dataset flags for state-based (keypoints) Push-T."""
    zarr = find_zarr(zarr)
    if zarr is not None:
        from .convert import convert_pusht

        root = keypoints_root(data_dir)
        if converted(data_dir):
            print(f"[data] reusing {root}", flush=True)
        else:
            print(f"[data] converting {zarr} -> {root}", flush=True)
            convert_pusht(zarr, root, variant="keypoints", repo_id="local/pusht_keypoints", overwrite=True)
        return ["--dataset.repo_id=local/pusht_keypoints", f"--dataset.root={root}"]
    if hub_offline():
        raise NoPushTDataError(
            "no Push-T data: pass --zarr /path/to/pusht_cchi_v7_replay.zarr (or set SDP_PUSHT_ZARR), "
            f"or go online (unset HF_HUB_OFFLINE) to download {HUB_KEYPOINTS} from the Hub."
        )
    print(f"[data] using {HUB_KEYPOINTS} from the Hugging Face Hub", flush=True)
    return [f"--dataset.repo_id={HUB_KEYPOINTS}"]
