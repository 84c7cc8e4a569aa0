"""SDP under LeRobot's RTC engine (`lerobot-rollout --inference.type=rtc`): the call shape LeRobot
checks, the result timed from the observation's tick (its slot, the leftover, the next chunk) driven
through LeRobot's own ActionQueue on the engine's clock, and the clear error when the engine calls
more often than once per chunk."""

import math

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
    # timed from the frame's tick: a slot for that tick (the engine drops it), then the chunk
    assert first.shape == (1, 1 + tb, 2) and len(calls) == policy.geometry.steps_per_call
    queue.merge(first[0], first[0], real_delay=1)  # a call faster than a tick: the engine drops one
    assert torch.equal(queue.get(), first[0, 1])  # the chunk's first action runs first
    for _ in range(tb - 3):
        queue.get()
    left = queue.get_left_over()
    assert left.shape[0] == 2
    padded = _normalize_prev_actions_length(left, target_steps=horizon)  # zero rows, as the engine does
    second = policy.predict_action_chunk(
        frame(cfg, 2), generator=g, inference_delay=1, prev_chunk_left_over=padded
    )
    assert second.shape == (1, 1 + 2 + tb, 2) and len(calls) == 2 * policy.geometry.steps_per_call
    assert torch.equal(second[0, 1:3], left)  # after the frame's tick the robot finishes the chunk

    # the new part is the stream's next chunk, each call's frame repeated as its history
    def history(seed):
        return {
            k: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k, v in observation(cfg, 1, seed=seed).items()
        }

    reference.predict_action_chunk(history(1), generator=g_ref)
    torch.testing.assert_close(second[:, 3:], reference.predict_action_chunk(history(2), generator=g_ref))


def test_rtc_called_more_often_than_once_per_chunk_is_a_clear_error():
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    policy.predict_action_chunk(frame(cfg, 1), inference_delay=0, prev_chunk_left_over=None)
    full = torch.rand(cfg.n_action_steps, 2) + 0.1  # a whole chunk still to execute
    with pytest.raises(ValueError, match=r"--inference\.queue_threshold=K` with K < 4"):
        policy.predict_action_chunk(frame(cfg, 2), inference_delay=1, prev_chunk_left_over=full)


def test_a_delay_trained_policy_commits_the_frames_own_action_and_the_leftover():
    """Trained with max_delay, the chunk after the leftover is the one that follows it: the action the
    robot ran at the frame's tick and the leftover enter the denoised sequence clean, as in training,
    where the observation of tick t precedes its own action."""
    cfg = tiny_config(max_delay=3)
    tb, horizon = cfg.n_action_steps, 10
    policy = SDPPolicy(cfg).eval()
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(policy.state_dict())
    queue = ActionQueue(RTCConfig(execution_horizon=horizon))
    g, g_ref = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    first = policy.predict_action_chunk(
        frame(cfg, 1), generator=g, inference_delay=0, prev_chunk_left_over=None
    )
    queue.merge(first[0], first[0], real_delay=1)
    for _ in range(tb - 2):
        queue.get()
    left = queue.get_left_over()
    padded = _normalize_prev_actions_length(left, target_steps=horizon)
    second = policy.predict_action_chunk(
        frame(cfg, 2), generator=g, inference_delay=1, prev_chunk_left_over=padded
    )
    assert torch.equal(second[0, 1:3], left)

    def history(seed):
        return {
            k: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k, v in observation(cfg, 1, seed=seed).items()
        }

    reference.predict_action_chunk(history(1), generator=g_ref)
    expected = reference.predict_action_chunk(history(2), generator=g_ref, committed=3)
    torch.testing.assert_close(second[:, 3:], expected)

    # more actions left than the policy was trained to commit: the fix is named
    policy.predict_action_chunk(frame(cfg, 3), inference_delay=0, prev_chunk_left_over=None)
    three = _normalize_prev_actions_length(torch.rand(3, 2) + 0.1, target_steps=horizon)
    with pytest.raises(ValueError, match=r"queue_threshold=K` with K <= 2"):
        policy.predict_action_chunk(frame(cfg, 4), inference_delay=1, prev_chunk_left_over=three)


@pytest.mark.parametrize(
    ("max_delay", "k", "latency"), [(0, 0, 0.3), (0, 1, 1.5), (3, 0, 0.3), (3, 1, 0.3), (3, 2, 1.5)]
)
def test_on_the_engines_clock_every_streamed_action_runs_once_k_plus_1_ticks_after_its_frame(
    max_delay, k, latency
):
    """LeRobot's RTC engine on a simulated clock, in its own order: each tick the loop publishes the
    tick's frame and sends the queue's next action; once the queue is down to K (`queue_threshold`)
    the thread calls on that frame, and `latency` ticks later the result replaces the queue after its
    first ceil(latency) actions (LeRobot's ActionQueue.merge). The robot never waits after the first
    chunk, runs every streamed action exactly once, in order, each chunk from K + 1 ticks after the
    frame it was built from; a policy trained with max_delay is told (K + 1 committed slots)."""
    horizon = 10
    cfg = tiny_config(max_delay=max_delay)
    policy = SDPPolicy(cfg).eval()
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(policy.state_dict())
    queue = ActionQueue(RTCConfig(execution_horizon=horizon))
    pending, calls, ran = None, [], []
    torch.manual_seed(0)
    for tick in range(40):
        if pending is not None and pending[0] < tick:  # the result came in before this tick's action
            _, result, index_before = pending
            queue.merge(result[0], result[0], math.ceil(latency), action_index_before_inference=index_before)
            pending = None
        ran.append(queue.get())
        if pending is None and queue.qsize() <= k:  # the thread's call, right after the action went
            left = queue.get_left_over()
            padded = None if left is None else _normalize_prev_actions_length(left, target_steps=horizon)
            result = policy.predict_action_chunk(
                frame(cfg, tick), inference_delay=1, prev_chunk_left_over=padded
            )
            n_left = 0 if left is None else len(left)
            calls.append((tick, n_left, result[0, 1 + n_left :].clone()))  # the new chunk
            pending = (tick + latency, result, queue.get_action_index())
    first_run = next(i for i, a in enumerate(ran) if a is not None)
    assert all(a is not None for a in ran[first_run:])  # never a tick without an action
    assert len(calls) >= 8 and all(n_left == k for _, n_left, _ in calls[1:])
    # the engine drops ceil(latency) actions of every result, of an episode's first one too, though the
    # robot ran none of it (LeRobot's delay model, the same for every policy): a slower first call
    # loses ceil(latency) - 1 actions of the first chunk; from then on nothing is lost
    lost = math.ceil(latency) - 1
    streamed = torch.cat([calls[0][2][lost:], *(chunk for _, _, chunk in calls[1:])])
    assert torch.equal(torch.stack(ran[first_run:]), streamed[: len(ran) - first_run])  # once each, in order
    for i, (tick, _, _) in enumerate(calls[1:], start=1):
        start = first_run + i * cfg.n_action_steps - lost
        assert start >= len(ran) or start == tick + k + 1  # the frame of `tick`, its chunk from tick + K + 1

    def history(seed):
        return {
            k_: v.unsqueeze(1).expand(-1, cfg.n_obs_steps, *v.shape[1:])
            for k_, v in observation(cfg, 1, seed=seed).items()
        }

    torch.manual_seed(0)
    expected = [reference.predict_action_chunk(history(calls[0][0]))]
    for tick, n_left, _ in calls[1:]:
        expected.append(
            reference.predict_action_chunk(history(tick), committed=n_left + 1 if max_delay else 0)
        )
    for (_, _, chunk), reference_chunk in zip(calls, expected, strict=True):
        torch.testing.assert_close(chunk, reference_chunk[0])


def test_the_rtc_engine_with_rtc_disabled_is_refused_with_the_flag():
    """`--inference.rtc.enabled=false` makes LeRobot's ActionQueue append results instead of replacing
    the queue: the leftover SDP returns would run twice. `lerobot-rollout` sets the engine's RTC
    config on the policy's config; SDP refuses the call and names the flag."""
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    policy.config.rtc_config = RTCConfig(enabled=False)
    with pytest.raises(ValueError, match=r"--inference\.rtc\.enabled=true"):
        policy.predict_action_chunk(frame(cfg, 1), inference_delay=0, prev_chunk_left_over=None)
    policy.config.rtc_config = RTCConfig(enabled=True)
    result = policy.predict_action_chunk(frame(cfg, 1), inference_delay=0, prev_chunk_left_over=None)
    assert result.shape[1] == 1 + cfg.n_action_steps
