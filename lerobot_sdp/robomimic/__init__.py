"""robomimic's tasks (robosuite) for LeRobot: `--env.type=robomimic`, the hdf5 converter, scripted
Lift, Can and Square demonstrators.

Importing this package registers the env config only; robosuite loads when an env is built.
"""

from .config import RobomimicEnvConfig

__all__ = ["RobomimicEnvConfig"]
