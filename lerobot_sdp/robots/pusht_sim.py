"""`PushTSim`: gym-pusht's Push-T behind LeRobot's `Robot` interface, for `lerobot-rollout`.

Observations are named scalars, as LeRobot robots declare them: the agent position `agent_x.pos`,
`agent_y.pos`, then the 8 block keypoints `block_kp{i}_x.pos`, `block_kp{i}_y.pos` (gym-pusht's
`environment_state` order). LeRobot keeps only scalar features ending in `.pos`/`.vel` and joins them,
in this order, into one `observation.state` (18,); SDP's preprocessor (`SplitStateStep`) splits it
into `observation.state` (2,) and `observation.environment_state` (16,), the features of a policy
trained on the converted Push-T dataset. The action is the agent's target position, `agent_x.pos`,
`agent_y.pos`, in pixels, passed to the env unclipped as `lerobot-eval` does.

Real time: the env advances one step (0.1 s at 10 Hz) per control tick of the wall clock, which
starts with the episode's first action, whether or not an action arrived. An action steps the
current tick; a tick that passes without one repeats the last target and counts as a missed tick
(a policy that stalls costs the robot what it costs on hardware), and an action early for its
tick becomes the target of the next. Observations are read after the clock is brought up to now.

One episode per connection (a reconnect starts a new one, from the configured seed): it ends on
success (coverage > 95 %) or after `episode_length` ticks, and the env then holds still (later
actions are counted, not applied). So every episode starts with a freshly started policy (its
buffer and history reset), never from a pusher that jumped to a new start under a policy still
streaming the last episode. Run one `lerobot-rollout` (or one robot
client) per episode: `--duration` at least `episode_length / fps` seconds.

For comparing inference engines the robot also records how far the commanded target jumped between
consecutive actions (`action_jump_px`: p50, p95, max; a chunk boundary that does not join up shows
as a jump).
"""

import json
import logging
import time
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected

from .config_pusht_sim import PushTSimConfig

logger = logging.getLogger(__name__)

N_KEYPOINTS = 8
AGENT_KEYS = ("agent_x.pos", "agent_y.pos")
KEYPOINT_KEYS = tuple(f"block_kp{i}_{axis}.pos" for i in range(N_KEYPOINTS) for axis in ("x", "y"))
PACING_CHECK_AFTER = 20  # actions before the rate check


class PushTSim(Robot):
    config_class = PushTSimConfig
    name = "pusht_sim"

    def __init__(self, config: PushTSimConfig):
        super().__init__(config)
        self.config = config
        self._env = None
        self._obs: dict[str, float] = {}
        self.episodes: list[dict[str, Any]] = []  # every finished episode, over connections
        self._start_episode()

    def _start_episode(self) -> None:
        """A connection's state from scratch: its episode, its clock and its counters."""
        self.actions_sent = 0
        self.ignored_commands = 0
        self.actions_after_end = 0
        self.early_actions = 0  # actions that came before their tick: they only replaced the target
        self.rewards: list[float] = []  # the episode's rewards, one per tick
        self.last_reward: float | None = None
        self._success = False
        self._over = False
        self._t0: float | None = None  # wall time of the episode's first action: tick 0
        self._t_first: float | None = None
        self._pacing_checked = False
        self._last_target: np.ndarray | None = None
        self.missed_ticks = 0
        self.action_jumps: list[float] = []
        self.longest_gap_s = 0.0  # the longest wall time between two actions (a stalled controller)
        self._t_last: float | None = None

    @property
    def observation_features(self) -> dict:
        return dict.fromkeys(AGENT_KEYS + KEYPOINT_KEYS, float)

    @property
    def action_features(self) -> dict:
        return dict.fromkeys(AGENT_KEYS, float)

    @property
    def is_connected(self) -> bool:
        return self._env is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        from gym_pusht.envs import PushTEnv  # here, not at import: LeRobot imports the config on every start

        self._env = PushTEnv(obs_type=self.config.obs_type)
        self._start_episode()  # a reconnect is a new episode, not the end of the last one
        obs, _ = self._env.reset(seed=self.config.seed)
        self._set_obs(obs)
        logger.info("pusht_sim connected (gym-pusht, %s, %d Hz)", self.config.obs_type, self.config.fps)

    def _set_obs(self, obs: dict[str, np.ndarray]) -> None:
        values = np.concatenate([obs["agent_pos"], obs["environment_state"]]).astype(float)
        self._obs = dict(zip(AGENT_KEYS + KEYPOINT_KEYS, values.tolist(), strict=True))

    def _due(self, now: float) -> int:
        """Control ticks begun by `now` since the first action (the nearest tick: jitter is no miss)."""
        return round((now - self._t0) * self.config.fps)

    def _catch_up(self, now: float) -> None:
        """Step every tick that passed without an action, holding the last target."""
        if self._t0 is None:
            return
        while not self._over and len(self.rewards) < self._due(now):
            self.missed_ticks += 1
            self._step(self._last_target)

    def _step(self, target: np.ndarray) -> None:
        obs, reward, terminated, _, info = self._env.step(target)
        self._set_obs(obs)
        self.last_reward = float(reward)
        self.rewards.append(self.last_reward)
        self._success = self._success or bool(info["is_success"])
        logger.debug("pusht_sim tick %d: reward %.3f", len(self.rewards), reward)
        if terminated or len(self.rewards) >= self.config.episode_length:
            self._end_episode()

    @check_if_not_connected
    def get_observation(self) -> dict[str, float]:
        self._catch_up(time.perf_counter())
        return dict(self._obs)

    @check_if_not_connected
    def send_action(self, action: dict[str, Any]) -> dict[str, float]:
        if set(action) & set(KEYPOINT_KEYS):
            # LeRobot's return-to-initial-position at shutdown commands every `.pos` observation, block
            # keypoints included: the block cannot be commanded, and moving the pusher back is no part
            # of the task, so the sim leaves the env as it is.
            if not self.ignored_commands:
                logger.info("pusht_sim ignores commands for block keypoints (return to initial position).")
            self.ignored_commands += 1
            return {k: self._obs[k] for k in AGENT_KEYS}
        missing = [k for k in AGENT_KEYS if k not in action]
        if missing:
            raise KeyError(f"pusht_sim action lacks {missing}; it takes {list(AGENT_KEYS)}.")
        target = np.array([float(action[k]) for k in AGENT_KEYS])
        now = time.perf_counter()
        if self._t0 is None:
            self._t0 = now
        self._catch_up(now)
        if self._over:  # finished before, or by the ticks held just now
            self.actions_after_end += 1
            return {k: self._obs[k] for k in AGENT_KEYS}
        if self._last_target is not None:
            self.action_jumps.append(float(np.linalg.norm(target - self._last_target)))
            self.longest_gap_s = max(self.longest_gap_s, now - self._t_last)
        self._last_target, self._t_last = target, now
        self.actions_sent += 1
        if len(self.rewards) <= self._due(now):
            self._step(target)
        else:
            self.early_actions += 1  # this tick already ran: the action is the next tick's target
        self._check_pacing(now)
        return dict(zip(AGENT_KEYS, target.tolist(), strict=True))

    def _check_pacing(self, now: float) -> None:
        if self._t_first is None:
            self._t_first = now
        elif not self._pacing_checked and self.actions_sent > PACING_CHECK_AFTER:
            self._pacing_checked = True
            rate = (self.actions_sent - 1) / max(now - self._t_first, 1e-9)
            if rate > 1.5 * self.config.fps:
                logger.warning(
                    "pusht_sim receives actions at %.0f Hz, Push-T runs at %d Hz: actions early for their "
                    "tick only replace the target. Pass --fps=%d to lerobot-rollout.",
                    rate,
                    self.config.fps,
                    self.config.fps,
                )

    def _episode_summary(self) -> dict[str, Any]:
        return {
            "steps": len(self.rewards),
            "max_reward": max(self.rewards, default=0.0),
            "sum_reward": float(sum(self.rewards)),
            "final_reward": self.rewards[-1] if self.rewards else 0.0,
            "success": self._success,
        }

    def _end_episode(self) -> None:
        self._over = True
        summary = self._episode_summary()
        self.episodes.append(summary)
        logger.info(
            "pusht_sim episode over: %d ticks (%d missed), max reward %.3f, success %s. The robot now "
            "holds still: one episode per run.",
            summary["steps"],
            self.missed_ticks,
            summary["max_reward"],
            summary["success"],
        )
        self._write_stats()

    def stats(self) -> dict[str, Any]:
        """The episode's seed, actions sent, finished episodes, and the episode under way (reward and
        success so far)."""
        return {
            "seed": self.config.seed,
            "actions_sent": self.actions_sent,
            "actions_after_end": self.actions_after_end,
            "early_actions": self.early_actions,
            "ignored_commands": self.ignored_commands,
            "missed_ticks": self.missed_ticks,
            "longest_gap_s": self.longest_gap_s,
            "action_jump_px": jump_stats(self.action_jumps),
            "last_reward": self.last_reward,
            "episodes": list(self.episodes),
            "current_episode": self._episode_summary(),
        }

    def _write_stats(self) -> None:
        if self.config.stats_path is not None:
            self.config.stats_path.parent.mkdir(parents=True, exist_ok=True)
            self.config.stats_path.write_text(json.dumps(self.stats(), indent=2))

    @check_if_not_connected
    def disconnect(self) -> None:
        current = self._episode_summary()
        logger.info(
            "pusht_sim disconnected after %d actions (%d missed ticks); episode %s: %d ticks, max reward "
            "%.3f, success %s",
            self.actions_sent,
            self.missed_ticks,
            "over" if self._over else "under way",
            current["steps"],
            current["max_reward"],
            current["success"],
        )
        self._write_stats()
        self._env.close()
        self._env = None


def jump_stats(jumps: list[float]) -> dict[str, float] | None:
    if not jumps:
        return None
    p50, p95 = np.percentile(jumps, [50, 95])
    return {"p50": float(p50), "p95": float(p95), "max": float(max(jumps)), "n": len(jumps)}
