"""Streaming invariants, observed through the policy's real U-Net calls."""

import pytest
import torch
from sdp_test_utils import PUSHT_STATS, history, observation, tiny_config

from lerobot_sdp import SDPPolicy


def record_unet_calls(policy):
    calls = []
    policy.ema_model.unet.register_forward_hook(lambda m, args, out: calls.append(args[1].clone()))
    return calls


def test_streaming_invariants_over_1000_calls():
    torch.manual_seed(0)
    cfg = tiny_config(n_action_steps=2, n_chunks=4, num_inference_steps=16)
    policy = SDPPolicy(cfg).eval()
    g, sched = policy.geometry, policy.model.schedule
    calls = record_unet_calls(policy)
    start_t = sched.train_timesteps(g.start_levels)
    s = g.steps_per_call
    chunk_starts = []
    for _step in range(1000):
        if len(policy._queues["action"]) == 0:
            chunk_starts.append(len(calls))
        action = policy.select_action(observation(cfg, batch_size=3))
        assert action.shape == (3, 2) and torch.isfinite(action).all()
    n_chunks_run = 1000 // cfg.n_action_steps
    assert len(chunk_starts) == n_chunks_run
    assert len(calls) == n_chunks_run * s  # exactly N/h denoiser calls per chunk, primer "zero" included
    for c, first in enumerate(chunk_starts):
        chunk_calls = calls[first : first + s]
        # the level pattern at the start of every call is identical: chunk i at (i+1)*N/h
        assert torch.equal(chunk_calls[0], start_t.expand(3, -1)), f"chunk {c}"
        # the last call steps chunk 0 from k=1, so the executed actions leave at level 0
        last_k = g.start_levels - (s - 1)
        assert torch.equal(chunk_calls[-1], sched.train_timesteps(last_k).expand(3, -1))
        assert (last_k[g.executed] == 1).all()


def test_executed_actions_are_clean():
    """With a denoiser that predicts a known clean trajectory, the executed chunk equals it exactly,
    which holds only if the executed slots reach level 0."""
    cfg = tiny_config(prediction_type="sample", clip_sample=False, num_inference_steps=10)
    policy = SDPPolicy(cfg).eval()
    target = torch.linspace(-0.5, 0.5, policy.geometry.horizon).view(1, -1, 1).expand(2, -1, 2)
    policy.ema_model.unet.forward = lambda x, t, global_cond=None: target.expand(x.shape[0], -1, -1)
    chunk = policy.predict_action_chunk(history(cfg, 2))
    torch.testing.assert_close(chunk, target[:, policy.geometry.executed], atol=1e-5, rtol=0)


@pytest.mark.parametrize("primer, extra", [("zero", 0), ("constant", 0), ("denoise", 1)])
def test_first_call_cost_follows_the_primer(primer, extra):
    cfg = tiny_config(action_primer=primer, num_inference_steps=10)
    policy = SDPPolicy(cfg, dataset_stats=PUSHT_STATS).eval()
    calls = record_unet_calls(policy)
    n, s = cfg.inference_steps, policy.geometry.steps_per_call
    policy.select_action(observation(cfg))
    assert len(calls) == s + extra * n  # denoise: N extra calls on the first chunk only
    for _ in range(cfg.n_action_steps):
        policy.select_action(observation(cfg))
    assert len(calls) == 2 * s + extra * n


def test_past_slots_are_renoised_to_chunk0_level():
    """After a shift the past-action slots hold executed actions noised to chunk 0's level, as in
    training (a clean-but-labelled-noisy past slot was a bug in the authors' code)."""
    cfg = tiny_config(n_obs_steps=3, num_inference_steps=10, prediction_type="sample", clip_sample=False)
    policy = SDPPolicy(cfg).eval()
    g = policy.geometry
    target = torch.zeros(1, g.horizon, 2)
    policy.ema_model.unet.forward = lambda x, t, global_cond=None: target.expand(x.shape[0], -1, -1)
    torch.manual_seed(0)
    policy.select_action(observation(cfg, batch_size=4096))
    past = policy._buffer.sample[:, : g.n_past]
    abar = policy.model.schedule.alpha_bar(policy.model.schedule.train_timesteps(g.start_levels[: g.n_past]))
    # clean value 0 noised to chunk 0's level: std = sqrt(1 - abar)
    torch.testing.assert_close(past.std(dim=0), (1 - abar).sqrt().expand(-1, 2), atol=0.05, rtol=0)


def test_reset_and_batch_size_change_start_a_new_stream():
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    policy.select_action(observation(cfg, batch_size=2))
    assert policy._buffer.batch_size == 2
    policy.reset()
    assert policy._buffer.sample is None and not policy._queues["action"]
    policy.select_action(observation(cfg, batch_size=2))
    action = policy.select_action(observation(cfg, batch_size=5))  # mid-chunk batch change
    assert action.shape == (5, 2) and policy._buffer.batch_size == 5
