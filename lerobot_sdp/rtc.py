"""LeRobot's RTC engine (`lerobot-rollout --inference.type=rtc`) as SDP reads it.

Every control tick the engine's loop reads an observation, publishes it, and sends the queue's next
action; its thread calls `predict_action_chunk(frame, inference_delay=d, prev_chunk_left_over=rest)`
once the queue is down to `--inference.queue_threshold` K actions, with the newest frame (it never
sees every tick, so the history is that frame repeated) and those K unexecuted actions, zero-padded
to `--inference.rtc.execution_horizon`. The engine reads the result as timed from the frame's own
tick t, whose action the robot has already sent: it drops the first ceil(latency / tick) actions,
at least one however fast the call (LeRobot's flow policies predict from tick t).

So SDP answers one slot for tick t (already run, always dropped), the rest (ticks t + 1 .. t + K),
then the buffer's next chunk (from t + K + 1): every streamed action runs once, none is skipped. A
policy trained with `max_delay` denoises that chunk with the action of tick t and the rest as K + 1
committed slots, as in training, where the observation of tick t precedes its own action. SDP
streams one chunk per call, so the engine must call once per chunk (docs/deployment.md), and it must
replace its queue with each result (`--inference.rtc.enabled=true`, the default; `engine_problem`).
"""

import torch
from torch import Tensor

from .configuration_sdp import SDPConfig


def engine_problem(config: SDPConfig) -> str | None:
    """Why the engine that set ``config.rtc_config`` (`lerobot-rollout` does) cannot run SDP, or None."""
    rtc_config = getattr(config, "rtc_config", None)
    if rtc_config is not None and not rtc_config.enabled:
        return (
            "SDP under the RTC engine needs --inference.rtc.enabled=true (the default): with it false, "
            "LeRobot's ActionQueue appends each result after the actions still queued instead of replacing "
            "them, and SDP's result repeats those actions (the leftover), so the robot would run them twice. "
            "Drop --inference.rtc.enabled=false, or use --inference.type=sync."
        )
    return None


def rest_of_last_chunk(config: SDPConfig, left_over: Tensor) -> Tensor:
    """The previous chunk's unexecuted actions (T, A), without the engine's zero padding; a clear error
    when the engine calls too early for one chunk per call, or with more left than `max_delay`."""
    tb, max_delay = config.n_action_steps, config.max_delay
    rows = left_over.reshape(-1, left_over.shape[-1])
    used = rows.abs().sum(-1) > 0  # the engine pads with zero rows; the last used row ends it
    n = int((used * torch.arange(1, len(used) + 1, device=used.device)).max())
    if rows.shape[0] < tb or n >= tb:
        raise ValueError(
            f"SDP under the RTC engine streams one chunk of {tb} actions per call, so it must be called "
            f"when fewer than {tb} actions are left (got {n} left of {rows.shape[0]} passed). Run "
            f"`lerobot-rollout --inference.type=rtc --inference.queue_threshold=K` with K < {tb} "
            f"(about the inference time in control ticks) and --inference.rtc.execution_horizon >= {tb}."
        )
    if max_delay and committed_under_rtc(n) > max_delay:
        raise ValueError(
            f"This SDP policy was trained for at most max_delay={max_delay} committed actions, and the "
            f"RTC engine called with {n} left, which with the action of the observation's own tick makes "
            f"{committed_under_rtc(n)}. Run `lerobot-rollout --inference.type=rtc "
            f"--inference.queue_threshold=K` with K <= {max_delay - 1} (the inference time in control "
            "ticks, rounded up, less one), or train with a larger `--policy.max_delay`."
        )
    return rows[:n]


def committed_under_rtc(n_left: int) -> int:
    """Actions decided before a chunk the engine asks for with ``n_left`` unexecuted: those and the
    action of the observation's own tick."""
    return n_left + 1


def engine_result(rest: Tensor | None, chunk: Tensor) -> Tensor:
    """What the engine expects back, timed from the observation's tick: a slot for that tick (already
    run; the engine drops it, so it repeats the next action), the rest (T, A) for every batch row,
    then the new chunk."""
    following = chunk
    if rest is not None:
        following = torch.cat([rest.to(chunk).unsqueeze(0).expand(chunk.shape[0], -1, -1), chunk], dim=1)
    return torch.cat([following[:, :1], following], dim=1)
