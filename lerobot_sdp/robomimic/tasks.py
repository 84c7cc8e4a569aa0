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


@dataclass(frozen=True)
class TaskSpec:
    """One robomimic task: how to build it in robosuite and what its observations look like."""

    name: str  # the `--env.task` value (robomimic's env_name)
    robosuite_env: str  # the robosuite environment class name
    n_arms: int
    object_dim: int  # size of robosuite's "object-state" (robomimic's "object" key)
    episode_length: int  # robomimic's evaluation horizon
    cameras: tuple[str, ...]  # robomimic's image-dataset cameras
    image_size: int  # robomimic's image-dataset resolution (square)
    description: str  # the LeRobot task string, shared by the env and recorded datasets
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
            f"robot{arm}_{key}_{i}" for arm in range(self.n_arms) for key, size in ARM_STATE_KEYS for i in range(size)
        ]

    @property
    def action_names(self) -> list[str]:
        parts = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
        return [f"robot{arm}_{part}" for arm in range(self.n_arms) for part in parts]


_SINGLE_ARM_CAMERAS = ("agentview", "robot0_eye_in_hand")

TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        TaskSpec("Lift", "Lift", 1, 10, 400, _SINGLE_ARM_CAMERAS, 84, "lift the cube"),
        TaskSpec("PickPlaceCan", "PickPlaceCan", 1, 14, 400, _SINGLE_ARM_CAMERAS, 84, "place the can in its bin"),
        TaskSpec(
            "NutAssemblySquare", "NutAssemblySquare", 1, 14, 400, _SINGLE_ARM_CAMERAS, 84,
            "fit the square nut onto the square peg",
        ),
        TaskSpec(
            "TwoArmTransport", "TwoArmTransport", 2, 41, 700,
            ("shouldercamera0", "shouldercamera1", "robot0_eye_in_hand", "robot1_eye_in_hand"), 84,
            "transport the hammer to the other bin",
            # robomimic's "single-arm-opposed": the two Pandas face each other across the table.
            env_configuration="opposed",
        ),
        TaskSpec("ToolHang", "ToolHang", 1, 44, 700, ("sideview", "robot0_eye_in_hand"), 240, "hang the tool on the frame"),
    )
}


def get_task(name: str) -> TaskSpec:
    """The spec of a task by its robomimic name, with the valid names in the error."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"Unknown robomimic task {name!r}: use one of {sorted(TASKS)}.") from None
