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
    """Push-T in simulation. `lerobot-rollout` paces the loop: pass `--fps=10` (Push-T's control rate;
    the rollout default is 30) so that one `send_action`, one 0.1 s env step, takes 0.1 s of wall time.

    An episode ends on success (coverage > 95 %) or after `episode_length` actions; the env then resets
    by itself and the rollout goes on. Each episode's reward and success are logged and, with
    `stats_path`, written as JSON.
    """

    obs_type: str = "environment_state_agent_pos"
    episode_length: int = 300
    seed: int | None = 0  # seeds the first reset; later episodes draw from the env's RNG
    fps: int = 10  # the env's control rate, used to warn when actions arrive faster
    stats_path: Path | None = None  # JSON: actions sent, per-episode reward and success

    def __post_init__(self):
        super().__post_init__()
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"pusht_sim obs_type must be one of {OBS_TYPES}, got {self.obs_type!r}.")
        if self.episode_length <= 0:
            raise ValueError(f"episode_length must be positive, got {self.episode_length}.")
