"""The five robomimic tasks as robosuite builds them: names, robots, horizons, observation layout.

Pure data, no robosuite import: the env config derives LeRobot features from it without the
`robomimic` extra installed. Settings follow robomimic's dataset metadata (Panda arms, OSC_POSE at
20 Hz, sparse reward) and its evaluation horizons (400 steps; 700 for Transport and Tool-hang).
"""

from dataclasses import dataclass

# robomimic's low-dimensional proprioception per arm, in robomimic's order, with sizes.
ARM_STATE_KEYS: tuple[tuple[str, int], ...] = (("eef_pos", 3), ("eef_quat", 4), ("gripper_qpos", 2))
# OSC_POSE delta (3 position + 3 axis-angle) plus one gripper command, per arm.
ARM_ACTION_DIM = 7
CONTROL_FREQ = 20
# robomimic's two observation settings: "low_dim" = proprioception + object state,
# "image" = proprioception + camera images (robomimic's image datasets carry no object state).
OBS_TYPES = ("low_dim", "image")


def check_obs_type(obs_type: str) -> None:
    if obs_type not in OBS_TYPES:
        raise ValueError(f"Unknown robomimic obs_type {obs_type!r}: use one of {list(OBS_TYPES)}.")


@dataclass(frozen=True)
class TaskSpec:
    """One robomimic task: how to build it in robosuite and what its observations look like."""

    name: str  # the `--env.task` value: robomimic's env_name, which is robosuite's environment class
    object_dim: int  # size of robosuite's "object-state" (robomimic's "object" key)
    description: str  # the LeRobot task string, shared by the env and recorded datasets
    # The defaults are the single-arm tasks' (Lift, Can, Square) settings.
    n_arms: int = 1
    episode_length: int = 400  # robomimic's evaluation horizon
    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")  # robomimic's image-dataset cameras
    image_size: int = 84  # robomimic's image-dataset resolution (square)
    env_configuration: str = "default"

    @property
    def state_dim(self) -> int:
        return self.n_arms * sum(size for _, size in ARM_STATE_KEYS)

    @property
    def action_dim(self) -> int:
        return self.n_arms * ARM_ACTION_DIM

    @property
    def state_keys(self) -> list[str]:
        """robosuite observation keys concatenated into `observation.state`, in order."""
        return [f"robot{arm}_{key}" for arm in range(self.n_arms) for key, _ in ARM_STATE_KEYS]

    @property
    def state_names(self) -> list[str]:
        """One name per `observation.state` entry (LeRobot feature `names`)."""
        return [
            f"robot{arm}_{key}_{i}"
            for arm in range(self.n_arms)
            for key, size in ARM_STATE_KEYS
            for i in range(size)
        ]

    @property
    def action_names(self) -> list[str]:
        parts = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
        return [f"robot{arm}_{part}" for arm in range(self.n_arms) for part in parts]


_TASK_SPECS = (
    TaskSpec("Lift", object_dim=10, description="lift the cube"),
    TaskSpec("PickPlaceCan", object_dim=14, description="place the can in its bin"),
    TaskSpec("NutAssemblySquare", object_dim=14, description="fit the square nut onto the square peg"),
    TaskSpec(
        "TwoArmTransport",
        object_dim=41,
        description="transport the hammer to the other bin",
        n_arms=2,
        episode_length=700,
        cameras=("shouldercamera0", "shouldercamera1", "robot0_eye_in_hand", "robot1_eye_in_hand"),
        # robomimic's "single-arm-opposed": the two Pandas face each other across the table.
        env_configuration="opposed",
    ),
    TaskSpec(
        "ToolHang",
        object_dim=44,
        description="hang the tool on the frame",
        episode_length=700,
        cameras=("sideview", "robot0_eye_in_hand"),
        image_size=240,
    ),
)
TASKS: dict[str, TaskSpec] = {spec.name: spec for spec in _TASK_SPECS}


def get_task(name: str) -> TaskSpec:
    """The spec of a task by its robomimic name, with the valid names in the error."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"Unknown robomimic task {name!r}: use one of {sorted(TASKS)}.") from None
