"""LeRobotDataset layout of robomimic demonstrations, shared by the hdf5 converter and the recorders.

Feature names are what `--env.type=robomimic` produces after LeRobot's `preprocess_observation`, so a
policy trained on these datasets runs in the env without a rename map. Images are stored losslessly
(PNG, not video) so converted values can be checked for equality.
"""

from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from ..dataset_writing import clear_output_dir
from .tasks import CONTROL_FREQ, TaskSpec, check_obs_type

REWARD = "next.reward"
DONE = "next.done"


def dataset_features(spec: TaskSpec, obs_type: str, cameras: list[str], image_size: int) -> dict:
    """LeRobot feature spec for one task and observation type ("low_dim" or "image")."""
    features = {
        OBS_STATE: {"dtype": "float32", "shape": (spec.state_dim,), "names": spec.state_names},
        ACTION: {"dtype": "float32", "shape": (spec.action_dim,), "names": spec.action_names},
        REWARD: {"dtype": "float32", "shape": (1,), "names": None},
        DONE: {"dtype": "bool", "shape": (1,), "names": None},
    }
    check_obs_type(obs_type)
    if obs_type == "low_dim":
        features[OBS_ENV_STATE] = {"dtype": "float32", "shape": (spec.object_dim,), "names": None}
    else:
        for cam in cameras:
            features[f"{OBS_IMAGES}.{cam}"] = {
                "dtype": "image",
                "shape": (image_size, image_size, 3),
                "names": ["height", "width", "channel"],
            }
    return features


def make_frame(obs: dict, action: np.ndarray, reward: float, done: bool, task: str) -> dict:
    """One LeRobot frame from an env-format observation (agent_pos / environment_state / pixels)."""
    frame = {
        OBS_STATE: np.asarray(obs["agent_pos"], dtype=np.float32),
        ACTION: np.asarray(action, dtype=np.float32),
        REWARD: np.array([reward], dtype=np.float32),
        DONE: np.array([done], dtype=bool),
        "task": task,
    }
    if "environment_state" in obs:
        frame[OBS_ENV_STATE] = np.asarray(obs["environment_state"], dtype=np.float32)
    for cam, image in obs.get("pixels", {}).items():
        frame[f"{OBS_IMAGES}.{cam}"] = image
    return frame


def create_dataset(repo_id: str, root: Path, features: dict, overwrite: bool) -> LeRobotDataset:
    """An empty local dataset at `root`, refusing to replace an existing one unless `overwrite`."""
    clear_output_dir(root, overwrite)
    return LeRobotDataset.create(
        repo_id=repo_id, fps=CONTROL_FREQ, features=features, root=root, robot_type="panda", use_videos=False
    )
