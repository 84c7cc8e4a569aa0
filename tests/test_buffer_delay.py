"""The streaming buffer with committed slots (inference delay, `StreamingBuffer.window`): a call made
while d actions of the last chunk are still to run denoises those d actions as clean slots and
returns the chunk that follows them; the next buffer is in the usual layout.

The buffer is driven by an oracle denoiser that knows the true action sequence (a smooth random
walk) and where the window sits in it. DDIM with x0 prediction makes every slot exact at k = 0, so
the executed chunk *is* the truth at the oracle's alignment: a chunk taken from the wrong slots, or
a buffer shifted by the wrong amount, shows as a chunk from the wrong time.
"""

import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler
from sdp_test_utils import stream_step_with

from lerobot_sdp.buffer import StreamingBuffer, StreamResetError
from lerobot_sdp.geometry import ChunkGeometry
from lerobot_sdp.schedule import PerSlotSchedule

TO, TB, H, N, MAX_DELAY, A = 2, 4, 2, 10, 3, 2
N_PAST = TO - 1


def make_buffer(kind: str = "DDIM") -> tuple[StreamingBuffer, object]:
    cls = DDIMScheduler if kind == "DDIM" else DDPMScheduler
    scheduler = cls(
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=False,
        prediction_type="sample",
    )
    geometry = ChunkGeometry(TO, TB, H, N, downsampling=4, max_delay=MAX_DELAY)
    return StreamingBuffer(geometry, PerSlotSchedule(scheduler, N)), scheduler


def random_walk(length: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.05 * torch.randn(1, length, A, generator=g)).cumsum(1).clamp(-1, 1)


class Oracle:
    """x0 = the truth from time `offset` on (slot 0 of the window at `offset`); records every call."""

    def __init__(self, truth: torch.Tensor):
        self.truth, self.offset, self.calls = truth, 0, []

    def __call__(self, sample: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        self.calls.append((sample.clone(), timesteps.clone()))
        return self.truth[:, self.offset : self.offset + sample.shape[1]]


def streamed(kind: str = "DDIM"):
    """A buffer primed at time 0 that has executed one chunk (times 1..4, after the past slot at 0)."""
    buffer, scheduler = make_buffer(kind)
    truth = random_walk()
    oracle = Oracle(truth)
    buffer.prime(torch.zeros(1, buffer.geometry.horizon, A), torch.Generator().manual_seed(1))
    first = stream_step_with(buffer, oracle, torch.Generator().manual_seed(2))
    torch.testing.assert_close(first, truth[:, N_PAST : N_PAST + TB])
    return buffer, scheduler, truth, oracle, first


@pytest.mark.parametrize("d", [1, 2, 3])
def test_the_chunk_after_the_committed_actions_is_returned_and_the_stream_goes_on(d):
    buffer, _, truth, oracle, _ = streamed()
    # The call's observation is at time TB - d + N_PAST (d actions of the first chunk still to run):
    # the window's slot 0 is the action before it.
    oracle.offset, oracle.calls = TB - d, []
    chunk = stream_step_with(buffer, oracle, committed=d)
    # the chunk is the one that starts when the committed actions end: times 5..8, not 5-d..8-d
    torch.testing.assert_close(chunk, truth[:, N_PAST + TB : N_PAST + 2 * TB])
    assert len(oracle.calls) == N // H
    # the next call, without delay, continues where this chunk ends
    oracle.offset = 2 * TB
    torch.testing.assert_close(
        stream_step_with(buffer, oracle, torch.Generator().manual_seed(4)),
        truth[:, N_PAST + 2 * TB : N_PAST + 3 * TB],
    )


@pytest.mark.parametrize("kind", ["DDIM", "DDPM"])
@pytest.mark.parametrize("d", [1, 3])
def test_committed_slots_are_the_last_chunks_end_clean_through_every_call(kind, d):
    buffer, _, _, oracle, first = streamed(kind)
    before = buffer.sample.clone()
    oracle.offset, oracle.calls = TB - d, []
    stream_step_with(buffer, oracle, committed=d)
    committed = slice(N_PAST, N_PAST + d)
    for sample, timesteps in oracle.calls:
        assert torch.equal(sample[:, committed], first[:, TB - d :])  # unchanged by every step
        assert (timesteps[:, committed] == -1).all()  # fed as clean, as in training
        assert (timesteps[:, N_PAST + d :] >= 0).all() and (timesteps[:, :N_PAST] >= 0).all()
    # the buffer's chunks moved d slots later, into the padding: the first call sees them there
    window = oracle.calls[0][0]
    n_future = H * TB
    assert torch.equal(window[:, N_PAST + d : N_PAST + d + n_future], before[:, N_PAST : N_PAST + n_future])


@pytest.mark.parametrize("d", [1, 2, 3])
def test_past_slots_hold_the_action_before_the_committed_ones_with_the_same_noise(d):
    buffer, scheduler, _, oracle, first = streamed()
    before = buffer.sample.clone()
    oracle.offset, oracle.calls = TB - d, []
    stream_step_with(buffer, oracle, committed=d)
    window = oracle.calls[0][0]
    # chunk 0's start level k = N/h: diffusers' set_timesteps(N) table, ascending
    scheduler.set_timesteps(N)
    t = sorted(int(x) for x in scheduler.timesteps)[N // H - 1]
    abar = scheduler.alphas_cumprod[t]
    a, b = abar.sqrt(), (1 - abar).sqrt()
    noise_now = (window[:, :N_PAST] - a * first[:, TB - d - N_PAST : TB - d]) / b
    noise_then = (before[:, :N_PAST] - a * first[:, TB - N_PAST :]) / b
    torch.testing.assert_close(noise_now, noise_then)


def test_committed_zero_is_the_plain_call():
    a, *_ = streamed()
    b, *_ = streamed()
    oracle_a, oracle_b = Oracle(random_walk()), Oracle(random_walk())
    oracle_a.offset = oracle_b.offset = TB
    plain = stream_step_with(a, oracle_a, torch.Generator().manual_seed(5))
    zero = stream_step_with(b, oracle_b, torch.Generator().manual_seed(5), committed=0)
    assert torch.equal(plain, zero) and torch.equal(a.sample, b.sample)


def test_committed_beyond_max_delay_or_before_any_chunk_is_refused():
    buffer, *_ = streamed()
    with pytest.raises(ValueError, match="max_delay=3"):
        stream_step_with(buffer, Oracle(random_walk()), committed=MAX_DELAY + 1)
    fresh, _ = make_buffer()
    fresh.prime(torch.zeros(1, fresh.geometry.horizon, A))
    with pytest.raises(ValueError, match="first chunk starts right after its observation"):
        stream_step_with(fresh, Oracle(random_walk()), committed=1)


@pytest.mark.parametrize("d", [0, 2])
def test_a_clear_during_a_call_is_not_undone_when_the_call_ends(d):
    buffer, _, _, oracle, _ = streamed()
    oracle.offset = TB - d

    def clearing(sample, timesteps):
        buffer.clear()  # e.g. policy.reset() from the control thread while inference runs
        return oracle(sample, timesteps)

    with pytest.raises(StreamResetError, match="belongs to the episode that ended"):
        stream_step_with(buffer, clearing, committed=d)  # never handed on: it would run in the next one
    assert buffer.sample is None and buffer.last_chunk is None
