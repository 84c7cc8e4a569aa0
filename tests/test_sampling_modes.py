"""`--policy.sampling`: SDP's stream and the two diagnostic samplers ("fresh", "full_denoise")."""

import pytest
import torch
from diffusers import DDIMScheduler
from sdp_test_utils import history, observation, tiny_config

from lerobot_sdp import SDPConfig, SDPPolicy


def _policy(**overrides) -> SDPPolicy:
    torch.manual_seed(0)
    return SDPPolicy(tiny_config(noise_scheduler_type="DDIM", **overrides)).eval()


def _same_weights(policy: SDPPolicy, **overrides) -> SDPPolicy:
    other = SDPPolicy(tiny_config(noise_scheduler_type="DDIM", **overrides)).eval()
    other.load_state_dict(policy.state_dict())
    return other


def _calls_per_chunk(policy: SDPPolicy, chunks: int = 3) -> list[int]:
    """Denoiser (U-Net) calls of each of `chunks` executed chunks, run through select_action."""
    calls = []
    hook = policy._sampling_model().unet.register_forward_hook(lambda *_: calls.append(1))
    per_chunk = []
    try:
        for chunk in range(chunks):
            before = len(calls)
            for step in range(policy.config.n_action_steps):
                policy.select_action(observation(policy.config, seed=10 * chunk + step))
            per_chunk.append(len(calls) - before)
    finally:
        hook.remove()
    return per_chunk


@pytest.mark.parametrize(
    ("sampling", "expected"),
    # tiny config: N = 10, h = 2; the zero primer makes no call, "fresh" primes by a full denoise
    [("stream", [5, 5, 5]), ("fresh", [15, 15, 15]), ("full_denoise", [10, 10, 10])],
)
def test_denoiser_calls_per_chunk(sampling, expected):
    assert _calls_per_chunk(_policy(sampling=sampling)) == expected


def test_stream_carries_the_buffer_over_and_fresh_does_not():
    """After a chunk, the stream keeps its buffer (the next chunk is already partly denoised); "fresh"
    drops it before each chunk and "full_denoise" never fills it."""
    for sampling, kept in (("stream", True), ("fresh", True), ("full_denoise", False)):
        policy = _policy(sampling=sampling)
        _calls_per_chunk(policy, chunks=1)
        assert (policy._buffer.sample is not None) == kept, sampling
    # the difference shows in the actions: the stream's second chunk depends on the first observation
    fresh = _policy(sampling="fresh")
    stream = _same_weights(fresh, sampling="stream", action_primer="denoise")
    second = []
    for policy in (fresh, stream):
        policy.reset()
        gen = torch.Generator().manual_seed(1)
        policy.predict_action_chunk(history(policy.config), generator=gen)
        second.append(policy.predict_action_chunk(history(policy.config), generator=gen))
    assert not torch.allclose(second[0], second[1])


def test_fresh_is_the_stream_with_its_buffer_cleared_before_every_chunk():
    """The diagnostic as first measured: SDP's stream with the `denoise` primer, its buffer cleared
    before each chunk. "fresh" primes by a full denoise whatever `action_primer` says."""
    fresh = _policy(sampling="fresh", action_primer="zero")
    reference = _same_weights(fresh, sampling="stream", action_primer="denoise")
    gens = [torch.Generator().manual_seed(7) for _ in range(2)]
    for chunk in range(3):
        batch = {k: v + chunk for k, v in history(fresh.config).items()}
        reference._buffer.clear()
        expected = reference.predict_action_chunk(batch, generator=gens[1])
        assert torch.equal(fresh.predict_action_chunk(batch, generator=gens[0]), expected), chunk


def test_full_denoise_is_diffusers_ddim_with_every_slot_at_one_level():
    """Independent computation: diffusers' DDIMScheduler loop on the policy's U-Net, all slots at the
    loop's timestep, from the same initial noise; the executed chunk is slots To-1 .. To-1+Tb."""
    policy = _policy(sampling="full_denoise")
    cfg, model = policy.config, policy._sampling_model()
    batch = history(cfg, batch_size=3)
    chunk = policy.predict_action_chunk(batch, generator=torch.Generator().manual_seed(5))

    scheduler = DDIMScheduler(
        num_train_timesteps=cfg.num_train_timesteps,
        beta_schedule=cfg.beta_schedule,
        clip_sample=cfg.clip_sample,
        clip_sample_range=cfg.clip_sample_range,
        prediction_type=cfg.prediction_type,
    )
    scheduler.set_timesteps(cfg.num_inference_steps)
    x = torch.randn(3, cfg.horizon, 2, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        cond = model.global_conditioning(batch)
        for t in scheduler.timesteps:
            eps = model.unet(x, torch.full((3, cfg.horizon), int(t)), global_cond=cond)
            x = scheduler.step(eps, t, x).prev_sample
    start = cfg.n_obs_steps - 1
    torch.testing.assert_close(chunk, x[:, start : start + cfg.n_action_steps], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("sampling", ["fresh", "full_denoise"])
def test_diagnostic_samplers_refuse_committed_actions(sampling):
    policy = _policy(sampling=sampling, max_delay=1)
    with pytest.raises(ValueError, match=r"use `--policy\.sampling=stream`"):
        policy.predict_action_chunk(history(policy.config), committed=1)


def test_full_denoise_refuses_a_non_finite_observation():
    policy = _policy(sampling="full_denoise")
    batch = history(policy.config)
    batch["observation.state"][0, -1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"observation\.state"):
        policy.predict_action_chunk(batch)


def test_unknown_sampling_is_named():
    with pytest.raises(ValueError, match=r"`sampling` must be one of \['stream', 'fresh', 'full_denoise'\]"):
        SDPConfig(sampling="afresh")
