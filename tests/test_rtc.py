"""SDP under LeRobot's RTC engine (`lerobot-rollout --inference.type=rtc`): the call shape LeRobot
checks, the leftover-then-next-chunk result driven through LeRobot's own ActionQueue, and the clear
error when the engine calls more often than once per chunk."""

import pytest
import torch
from lerobot.policies.rtc import ActionQueue
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.rollout.inference.rtc import _normalize_prev_actions_length, supports_rtc_inference
from sdp_test_utils import observation, tiny_config

from lerobot_sdp import SDPPolicy


def frame(cfg, seed):
    return {**observation(cfg, 1, seed=seed), "task": ["push the T"]}  # as the engine passes it


def test_lerobot_accepts_sdp_for_rtc():
    assert supports_rtc_inference(SDPPolicy(tiny_config()))


def test_rtc_calls_return_the_leftover_then_the_buffers_next_chunk():
    cfg = tiny_config()
    tb, horizon = cfg.n_action_steps, 10
    policy = SDPPolicy(cfg).eval()
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(policy.state_dict())
    calls = []
    policy.ema_model.unet.register_forward_hook(lambda *_: calls.append(1))
    queue = ActionQueue(RTCConfig(execution_horizon=horizon))
    g, g_ref = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)

    first = policy.predict_action_chunk(
        frame(cfg, 1), generator=g, inference_delay=0, prev_chunk_left_over=None
    )
    assert first.shape == (1, tb, 2) and len(calls) == policy.geometry.steps_per_call
    queue.merge(first[0], first[0], real_delay=1)  # the engine drops what ran during the call
    for _ in range(tb - 3):
        queue.get()
    left = queue.get_left_over()
    assert left.shape[0] == 2
    padded = _normalize_prev_actions_length(left, target_steps=horizon)  # zero rows, as the engine does
    second = policy.predict_action_chunk(
        frame(cfg, 2), generator=g, inference_delay=1, prev_chunk_left_over=padded
    )
    assert second.shape == (1, 2 + tb, 2) and len(calls) == 2 * policy.geometry.steps_per_call
    assert torch.equal(second[0, :2], left)  # the robot finishes the previous chunk first

    # the new part is the stream's next chunk, each call's frame repeated as its history
    def history(seed):
        return {
            k: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k, v in observation(cfg, 1, seed=seed).items()
        }

    reference.predict_action_chunk(history(1), generator=g_ref)
    torch.testing.assert_close(second[:, 2:], reference.predict_action_chunk(history(2), generator=g_ref))


def test_rtc_called_more_often_than_once_per_chunk_is_a_clear_error():
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    policy.predict_action_chunk(frame(cfg, 1), inference_delay=0, prev_chunk_left_over=None)
    full = torch.rand(cfg.n_action_steps, 2) + 0.1  # a whole chunk still to execute
    with pytest.raises(ValueError, match=r"--inference\.queue_threshold=K` with K < 4"):
        policy.predict_action_chunk(frame(cfg, 2), inference_delay=1, prev_chunk_left_over=full)


def test_a_delay_trained_policy_denoises_the_rtc_leftover_as_committed_slots():
    """Trained with max_delay, the chunk after the leftover is the one that follows it (the leftover
    enters the denoised sequence clean), not one denoised as if it started at the observation."""
    cfg = tiny_config(max_delay=2)
    tb, horizon = cfg.n_action_steps, 10
    policy = SDPPolicy(cfg).eval()
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(policy.state_dict())
    queue = ActionQueue(RTCConfig(execution_horizon=horizon))
    g, g_ref = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    first = policy.predict_action_chunk(
        frame(cfg, 1), generator=g, inference_delay=0, prev_chunk_left_over=None
    )
    queue.merge(first[0], first[0], real_delay=0)
    for _ in range(tb - 2):
        queue.get()
    left = queue.get_left_over()
    padded = _normalize_prev_actions_length(left, target_steps=horizon)
    second = policy.predict_action_chunk(
        frame(cfg, 2), generator=g, inference_delay=2, prev_chunk_left_over=padded
    )
    assert torch.equal(second[0, :2], left)

    def history(seed):
        return {
            k: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k, v in observation(cfg, 1, seed=seed).items()
        }

    reference.predict_action_chunk(history(1), generator=g_ref)
    expected = reference.predict_action_chunk(history(2), generator=g_ref, committed=2)
    torch.testing.assert_close(second[:, 2:], expected)

    # more actions left than the policy was trained to commit: the fix is named
    policy.predict_action_chunk(frame(cfg, 3), inference_delay=0, prev_chunk_left_over=None)
    three = _normalize_prev_actions_length(torch.rand(3, 2) + 0.1, target_steps=horizon)
    with pytest.raises(ValueError, match=r"queue_threshold=K` with K <= 2"):
        policy.predict_action_chunk(frame(cfg, 4), inference_delay=1, prev_chunk_left_over=three)


@pytest.mark.parametrize("max_delay", [0, 2])
def test_on_the_engines_clock_each_chunk_starts_threshold_ticks_after_its_observation(max_delay):
    """LeRobot's RTC engine on a simulated clock, with its own ActionQueue: the call starts when
    `queue_threshold` (K = 2) actions are left, takes d = 2 ticks, and its result replaces the queue
    after the d actions that ran meanwhile. Each new chunk's first action runs K ticks after the
    observation it was built from, the robot never waits, and a policy trained with max_delay is
    told (its chunk is the one denoised with those K actions committed)."""
    k = d = 2
    horizon = 10
    cfg = tiny_config(max_delay=max_delay)
    policy = SDPPolicy(cfg).eval()
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(policy.state_dict())
    queue = ActionQueue(RTCConfig(execution_horizon=horizon))
    pending, calls, ran = None, [], []
    torch.manual_seed(0)
    for tick in range(40):
        if pending is not None and pending[0] == tick:
            _, result, index_before = pending
            queue.merge(result[0], result[0], real_delay=d, action_index_before_inference=index_before)
            pending = None
        if pending is None and queue.qsize() <= k:
            left = queue.get_left_over()
            padded = None if left is None else _normalize_prev_actions_length(left, target_steps=horizon)
            result = policy.predict_action_chunk(
                frame(cfg, tick), inference_delay=d, prev_chunk_left_over=padded
            )
            n_left = 0 if left is None else len(left)
            calls.append((tick, n_left, result[0, n_left].clone()))  # the new chunk's first action
            ready = tick + (d if left is not None else 0)
            pending = (ready, result, queue.get_action_index())
            if ready == tick:
                queue.merge(result[0], result[0], real_delay=0)
                pending = None
        ran.append(queue.get())
    assert all(a is not None for a in ran)  # never a tick without an action
    assert len(calls) >= 8
    for tick, n_left, first in calls[1:]:
        assert n_left == k
        if tick + n_left < len(ran):
            assert torch.equal(ran[tick + n_left], first)  # observation at `tick`, its chunk from tick + K

    def history(seed):
        return {
            k_: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k_, v in observation(cfg, 1, seed=seed).items()
        }

    torch.manual_seed(0)
    expected = [reference.predict_action_chunk(history(calls[0][0]))]
    for tick, n_left, _ in calls[1:]:
        expected.append(reference.predict_action_chunk(history(tick), committed=n_left if max_delay else 0))
    for (_, _, first), chunk in zip(calls, expected, strict=True):
        torch.testing.assert_close(first, chunk[0, 0])
