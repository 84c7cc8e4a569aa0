"""Reading robomimic's hdf5 demonstrations into the robomimic env's observation format.

robomimic's layout: `data` (attrs `env_args`, a JSON string with env_name and env_kwargs), then per
demonstration `data/demo_<i>/obs/<key>` (T, ...), `actions` (T, A), `rewards` (T,), `dones` (T,);
optional `mask/<filter_key>` lists demo names (e.g. robomimic's train / valid splits).
"""

import json
from dataclasses import dataclass

import numpy as np

from .tasks import CONTROL_FREQ, TaskSpec, get_task

try:
    import h5py
except ModuleNotFoundError as err:
    raise ModuleNotFoundError(
        f"Reading robomimic hdf5 files needs h5py ({err}): pip install 'lerobot_policy_sdp[robomimic]'."
    ) from err


@dataclass
class Demo:
    """One demonstration, observations keyed as the robomimic env emits them."""

    name: str
    obs: dict  # "agent_pos" (T, S), then "environment_state" (T, O) or "pixels" {camera: (T, H, W, 3)}
    actions: np.ndarray  # (T, A)
    rewards: np.ndarray  # (T,)
    dones: np.ndarray  # (T,)

    def __len__(self) -> int:
        return len(self.actions)


def open_robomimic(path) -> h5py.File:
    """Open a robomimic file read-only, checking it has robomimic's `data` group."""
    f = h5py.File(path, "r")
    if "data" not in f:
        f.close()
        raise ValueError(f"{path} has no `data` group: it is not a robomimic demonstration file.")
    return f


def task_of(f: h5py.File, override: str | None = None) -> TaskSpec:
    """The task recorded in `data.attrs['env_args']` (or `override`), checked against our env."""
    env_args = json.loads(f["data"].attrs["env_args"]) if "env_args" in f["data"].attrs else None
    if override is None and env_args is None:
        raise ValueError(f"{f.filename} has no data.attrs['env_args']: name the task with --task.")
    spec = get_task(override or env_args["env_name"])
    control_freq = (env_args or {}).get("env_kwargs", {}).get("control_freq", CONTROL_FREQ)
    if control_freq != CONTROL_FREQ:
        raise ValueError(
            f"{f.filename} was recorded at {control_freq} Hz; robomimic's tasks (and this env) run at "
            f"{CONTROL_FREQ} Hz, so its actions would not replay here."
        )
    return spec


def demo_names(f: h5py.File, filter_key: str | None = None) -> list[str]:
    """Demonstration names in numeric order (demo_2 before demo_10), optionally one mask's subset."""
    if filter_key is None:
        names = [name for name in f["data"] if name.startswith("demo_")]
    else:
        masks = f.get("mask", {})
        if filter_key not in masks:
            raise ValueError(f"{f.filename} has no mask/{filter_key}: available filter keys {sorted(masks)}.")
        names = [name.decode() if isinstance(name, bytes) else str(name) for name in masks[filter_key][:]]
    if not names:
        raise ValueError(f"{f.filename} holds no demonstrations (no data/demo_* groups).")
    return sorted(names, key=lambda name: int(name.split("_")[-1]))


def _dataset(group: h5py.Group, key: str, hint: str) -> np.ndarray:
    if key not in group:
        raise KeyError(f"{group.name} has no `{key}` (it has {sorted(group)}). {hint}")
    return group[key][:]


def read_demo(f: h5py.File, name: str, spec: TaskSpec, obs_type: str, cameras: list[str]) -> Demo:
    """One demonstration as env-format arrays, with its length checked across all arrays."""
    group = f["data"][name]
    if "obs" not in group:
        raise KeyError(
            f"{group.name} has no `obs`: this is a raw robosuite recording (states only); extract "
            "observations first with robomimic's scripts/dataset_states_to_obs.py."
        )
    obs_group = group["obs"]
    hint = f"Is this a {spec.name} file with {spec.n_arms} arm(s)? Pass --task to override."
    obs = {"agent_pos": np.concatenate([_dataset(obs_group, key, hint) for key in spec.state_keys], axis=1)}
    if obs_type == "low_dim":
        obs["environment_state"] = _dataset(obs_group, "object", hint)
    else:
        hint = "Pick cameras this file has with --camera_names, or convert low_dim."
        obs["pixels"] = {cam: _dataset(obs_group, f"{cam}_image", hint) for cam in cameras}
    demo = Demo(
        name=name,
        obs=obs,
        actions=_dataset(group, "actions", hint),
        rewards=_dataset(group, "rewards", "robomimic's processed datasets carry per-step rewards."),
        dones=_dataset(group, "dones", "robomimic's processed datasets carry per-step dones."),
    )
    _check_shapes(demo, spec)
    return demo


def _check_shapes(demo: Demo, spec: TaskSpec) -> None:
    arrays = {"actions": demo.actions, "rewards": demo.rewards, "dones": demo.dones}
    arrays |= {key: value for key, value in demo.obs.items() if key != "pixels"}
    arrays |= {f"{cam}_image": image for cam, image in demo.obs.get("pixels", {}).items()}
    lengths = {key: len(value) for key, value in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"{demo.name}: arrays disagree on the episode length: {lengths}.")
    if demo.actions.shape[1:] != (spec.action_dim,):
        raise ValueError(
            f"{demo.name}: actions of shape {demo.actions.shape[1:]}, {spec.name} takes ({spec.action_dim},)."
        )
    if "environment_state" in demo.obs and demo.obs["environment_state"].shape[1:] != (spec.object_dim,):
        raise ValueError(
            f"{demo.name}: object state of shape {demo.obs['environment_state'].shape[1:]}, "
            f"{spec.name} in robosuite 1.5 has ({spec.object_dim},)."
        )
