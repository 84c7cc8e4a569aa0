"""Inference delay on a virtual clock: a policy whose chunks take `delay` control ticks to compute,
driven by LeRobot's own evaluation rollout.

`DelayedControl` stands in for the policy in `lerobot.scripts.lerobot_eval.eval_policy`: every call
of its `select_action` is one control tick with that tick's observation. A chunk requested at tick
t sees the observations up to t and becomes available at t + `delay`; the robot meanwhile executes
what it already had (or holds its last target when it has nothing). Inference itself costs no time
on this clock, so the result depends only on the delay, never on how busy the machine is. An
episode's first chunk is computed before its first tick, the same for every mode.

Modes, which differ in when a chunk is requested and where its actions go:

- `blocking` (LeRobot's sync engine): request when nothing is left; the robot holds its last target
  for `delay` ticks, then runs the whole chunk.
- `naive_async` for LeRobot's `diffusion` (LeRobot's async inference): request when `delay` actions
  are left; the chunk's actions are timed from the observation's tick, so its first `delay` are in
  the past when it arrives and are dropped, the rest replaces the queue.
- `naive_async` for SDP (what SDP did before delay-aware streaming): request when `delay` actions are
  left and append the chunk after them; it was denoised as if it started right after the
  observation, so it runs `delay` ticks late.
- `delay_aware` for SDP trained with `max_delay`: the same timing, the actions left passed as
  `committed` (`SDPPolicy.predict_action_chunk`), so the chunk is denoised as the one that follows
  them.

The history a chunk is conditioned on is the last `n_obs_steps` frames, one tick apart, or with
`history="frame"` the newest frame repeated: what LeRobot's RTC engine gives a policy. An RTC engine
with `--inference.queue_threshold=K` is then SDP's `naive_async` / `delay_aware` at d = K + 1 (the
call comes as the action of the frame's tick goes out with K left; docs/deployment.md).
"""

from collections import deque

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from torch import Tensor

MODES = ("blocking", "naive_async", "delay_aware")
HISTORIES = ("full", "frame")


class DelayedControl(PreTrainedPolicy):
    """A trained policy (LeRobot `diffusion` or `sdp`) under inference delay `delay`, in `mode`."""

    config_class = PreTrainedConfig
    name = "delayed_control"

    def __init__(self, policy: PreTrainedPolicy, mode: str, delay: int, history: str = "full"):
        super().__init__(policy.config)
        problem = mode_problem(policy, mode, delay) or (
            None if history in HISTORIES else f"Unknown history {history!r}; choose from {list(HISTORIES)}."
        )
        if problem:
            raise ValueError(problem)
        self.policy, self.mode, self.delay, self.frames_only = policy, mode, delay, history == "frame"
        self.chunks = 0  # chunks requested, over all episodes
        self.held_ticks = 0  # ticks the robot had no action for, over all episodes
        self.reset()

    def reset(self) -> None:
        """A new episode: the policy's buffer and history, the queue and the clock start over."""
        self.policy.reset()
        self.history = {k: deque(maxlen=self.config.n_obs_steps) for k in self.config.input_features}
        self.queue: list[Tensor] = []  # (B, A) actions for the coming ticks
        self.pending: tuple[int, int, Tensor] | None = None  # (tick requested, tick ready, chunk)
        self.tick = 0
        self.last: Tensor | None = None

    def get_optim_params(self) -> dict:
        return self.policy.get_optim_params()

    def forward(self, batch: dict[str, Tensor]):
        return self.policy.forward(batch)

    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.policy.predict_action_chunk(batch, **kwargs)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One control tick: take the observation, merge a chunk that is ready, request one that is
        due, run the next action (or hold the last target)."""
        # LeRobot's own history: the first frame repeated to n_obs_steps at an episode's start
        self.history = populate_queues(self.history, {k: batch[k] for k in self.config.input_features})
        if self.pending is not None and self.pending[1] == self.tick:
            self._merge(*self.pending)
        if self.pending is None and self._due():
            self._request()
        if self.queue:
            self.last = self.queue.pop(0)
        else:
            self.held_ticks += 1
        self.tick += 1
        return self.last

    def _due(self) -> bool:
        if self.tick == 0:
            return True
        if self.mode == "blocking":
            return not self.queue
        return len(self.queue) <= self.delay

    def _request(self) -> None:
        frames = {k: [q[-1]] * len(q) if self.frames_only else list(q) for k, q in self.history.items()}
        history = {k: torch.stack(f, dim=1) for k, f in frames.items()}
        committed = len(self.queue) if self.mode == "delay_aware" else 0
        kwargs = {"committed": committed} if self.config.type == "sdp" else {}
        chunk = self.policy.predict_action_chunk(history, **kwargs)
        self.chunks += 1
        ready = self.tick if self.tick == 0 else self.tick + self.delay
        if ready == self.tick:
            self._merge(self.tick, ready, chunk)
        else:
            self.pending = (self.tick, ready, chunk)

    def _merge(self, requested: int, ready: int, chunk: Tensor) -> None:
        actions = list(chunk.transpose(0, 1))  # (B, A) per tick
        if self.mode == "naive_async" and self.config.type != "sdp":
            self.queue = actions[ready - requested :]  # timed from the observation: the elapsed are past
        else:
            self.queue = self.queue + actions  # after what the robot still had
        self.pending = None


def mode_problem(policy: PreTrainedPolicy, mode: str, delay: int) -> str | None:
    """Why `policy` cannot run in `mode` at `delay`, or None."""
    if mode not in MODES:
        return f"Unknown mode {mode!r}; choose from {list(MODES)}."
    if delay < 0:
        return f"The delay must be at least 0 ticks, got {delay}."
    chunk = policy.config.n_action_steps
    if mode != "blocking" and delay >= chunk:
        return (
            f"A delay of {delay} ticks is a whole chunk ({chunk} actions) or more: "
            f"{mode} would request a chunk before the last one arrived. Use delays below {chunk}."
        )
    if mode == "delay_aware":
        if policy.config.type != "sdp":
            return "delay_aware needs an SDP policy (committed slots); LeRobot's diffusion has none."
        max_delay = policy.config.max_delay
        if delay > max_delay:
            return f"This SDP policy was trained for delays up to max_delay={max_delay}, not {delay}."
    return None
