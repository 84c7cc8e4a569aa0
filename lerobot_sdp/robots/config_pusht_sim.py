"""`--robot.type=pusht_sim`: Push-T (gym-pusht) as a LeRobot robot.

Cheap to import (LeRobot imports it through the plugin shim on every CLI start): gym-pusht is imported
only when the robot connects. LeRobot finds the robot class by name, `PushTSimConfig` -> `PushTSim` in
`lerobot_sdp.robots.pusht_sim`.
"""

from dataclasses import dataclass
from pathlib import Path

from lerobot.robots.config import RobotConfig

OBS_TYPES = ("environment_state_agent_pos",)


@RobotConfig.register_subclass("pusht_sim")
@dataclass(kw_only=True)
class PushTSimConfig(RobotConfig):
    """Push-T in simulation, in real time. `lerobot-rollout` paces the loop: pass `--fps=10` (Push-T's
    control rate; the rollout default is 30). The env steps once per 0.1 s tick of the wall clock from
    the first action on; a tick without an action holds the last target (a missed tick).

    One episode per connection: it ends on success (coverage > 95 %) or after `episode_length` ticks,
    and the robot then holds still, so every episode starts with a fresh policy. Its reward, success
    and missed ticks are logged and, with `stats_path`, written as JSON.
    """

    obs_type: str = "environment_state_agent_pos"
    episode_length: int = 300
    seed: int | None = 0  # the episode's start (block pose), as lerobot-eval's episode seeds
    fps: int = 10  # the env's control rate: one env step per tick of the wall clock
    stats_path: Path | None = None  # JSON: actions sent, missed ticks, the episode's reward and success

    def __post_init__(self):
        super().__post_init__()
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"pusht_sim obs_type must be one of {OBS_TYPES}, got {self.obs_type!r}.")
        if self.episode_length <= 0:
            raise ValueError(f"episode_length must be positive, got {self.episode_length}.")
