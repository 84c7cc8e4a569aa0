"""Streaming invariants, observed through the policy's real U-Net calls. The buffer's contents are
pinned in test_buffer_contents.py."""

import math

import pytest
import torch
from diffusers import DDIMScheduler
from lerobot.configs import NormalizationMode
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


# Raw statistics that differ between state and action in every field, so that a primer that skipped
# a conversion (or used the wrong statistic) lands elsewhere.
PRIMER_STATS = {
    "observation.state": {
        "min": [10.0, 40.0],
        "max": [490.0, 500.0],
        "mean": [240.0, 270.0],
        "std": [110.0, 95.0],
    },
    "action": {"min": [5.0, 20.0], "max": [515.0, 505.0], "mean": [255.0, 250.0], "std": [90.0, 105.0]},
}


def textbook_normalise(raw, stats, mode):
    s = {k: torch.tensor(v) for k, v in stats.items()}
    if mode is NormalizationMode.MIN_MAX:
        return 2 * (raw - s["min"]) / (s["max"] - s["min"]) - 1
    return (raw - s["mean"]) / s["std"]


@pytest.mark.parametrize(
    "state_mode, action_mode",
    [
        (NormalizationMode.MIN_MAX, NormalizationMode.MIN_MAX),
        (NormalizationMode.MEAN_STD, NormalizationMode.MEAN_STD),
        (NormalizationMode.MEAN_STD, NormalizationMode.MIN_MAX),
    ],
)
def test_constant_primer_starts_from_the_newest_observation(state_mode, action_mode):
    """With To = 3 observations of different states, the executed first chunk is the *newest* state in
    action space, computed here with the textbook formulas from the raw statistics.

    The denoiser predicts zero noise and every chunk is one DDIM step (h = N), so chunk 0 is primed at
    k = 1 (t = 0) and its single step returns primer + sqrt((1 - abar_0) / abar_0) z: the primer, up to
    noise of std 0.025 that averages out over the batch."""
    cfg = tiny_config(
        n_obs_steps=3,
        n_action_steps=1,
        n_chunks=10,
        num_inference_steps=10,
        noise_scheduler_type="DDIM",
        prediction_type="epsilon",
        clip_sample=False,
        action_primer="constant",
        normalization_mapping={"STATE": state_mode, "ACTION": action_mode},
    )
    policy = SDPPolicy(cfg, dataset_stats=PRIMER_STATS).eval()
    policy.ema_model.unet.forward = lambda x, t, global_cond=None: torch.zeros_like(x)
    raw_states = torch.tensor([[60.0, 460.0], [250.0, 120.0], [420.0, 300.0]])  # oldest .. newest
    batch = 2048
    norm_states = textbook_normalise(raw_states, PRIMER_STATS["observation.state"], state_mode)
    obs = {
        "observation.state": norm_states.expand(batch, -1, -1),
        "observation.environment_state": torch.rand(batch, 3, 16),
    }
    chunk = policy.predict_action_chunk(obs, generator=torch.Generator().manual_seed(0))
    assert chunk.shape == (batch, 1, 2)
    as_actions = textbook_normalise(raw_states, PRIMER_STATS["action"], action_mode)  # (To, A)
    abar0 = float(DDIMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2").alphas_cumprod[0])
    tol = 5 * math.sqrt((1 - abar0) / abar0 / batch)
    mean = chunk[:, 0].double().mean(0).float()
    assert (mean - as_actions[-1]).abs().max() < tol, (
        f"primer {mean.tolist()}, newest {as_actions[-1].tolist()}"
    )
    assert ((as_actions[:-1] - as_actions[-1]).abs().amax(-1) > 100 * tol).all()  # older ones are far


def test_a_reset_while_a_call_primes_its_stream_keeps_nothing(monkeypatch):
    """A reset() from another thread between a call's "is the buffer empty?" and its prime (a client's
    Ready, an episode's end) wins: the call fails with the reason and the buffer stays empty, never
    primed from the old episode's observation."""
    from lerobot_sdp.buffer import StreamResetError

    policy = SDPPolicy(tiny_config()).eval()
    model = policy._sampling_model()
    primer = model.primer

    def primer_then_reset(*args, **kwargs):
        value = primer(*args, **kwargs)
        policy.reset()  # what another thread's reset() does while the primer is computed
        return value

    monkeypatch.setattr(model, "primer", primer_then_reset)
    with pytest.raises(StreamResetError, match="reset"):
        policy.predict_action_chunk(history(policy.config, batch_size=1))
    assert policy._buffer.sample is None
    monkeypatch.setattr(model, "primer", primer)
    assert policy.predict_action_chunk(history(policy.config, batch_size=1)).shape[1] == 4
