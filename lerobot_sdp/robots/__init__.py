"""Simulated robots for `lerobot-rollout`: `--robot.type=pusht_sim` (Push-T on gym-pusht, no hardware).

Importing this package registers the robot configs only; gym-pusht loads when a robot connects.
"""

from .config_pusht_sim import PushTSimConfig

__all__ = ["PushTSimConfig"]
