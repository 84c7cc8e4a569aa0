"""LeRobot's RTC engine (`lerobot-rollout --inference.type=rtc`) as SDP reads it.

The engine calls `predict_action_chunk(frame, inference_delay=d, prev_chunk_left_over=rest)` with one
frame (it never sees every control tick, so the history is that frame repeated) and the unexecuted
rest of what the last call returned, zero-padded to `--inference.rtc.execution_horizon`. SDP answers
that rest followed by the buffer's next chunk; the engine drops the first d actions (executed while
the call ran). SDP streams one chunk per call, so the engine must call once per chunk; a policy
trained with `max_delay` denoises the chunk with the rest as committed slots (docs/deployment.md).
"""

import torch
from torch import Tensor

from .configuration_sdp import SDPConfig


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
    if max_delay and n > max_delay:
        raise ValueError(
            f"This SDP policy was trained for at most max_delay={max_delay} actions left when a chunk "
            f"is requested, and the RTC engine called with {n} left. Run `lerobot-rollout "
            f"--inference.type=rtc --inference.queue_threshold=K` with K <= {max_delay} (the inference "
            "time in control ticks), or train with a larger `--policy.max_delay`."
        )
    return rows[:n]


def rest_then_chunk(rest: Tensor | None, chunk: Tensor) -> Tensor:
    """What the engine expects back: the rest (T, A), for every batch row, then the new chunk."""
    if rest is None:
        return chunk
    return torch.cat([rest.to(chunk).unsqueeze(0).expand(chunk.shape[0], -1, -1), chunk], dim=1)
