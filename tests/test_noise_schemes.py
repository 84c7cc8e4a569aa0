import pytest
import torch
from diffusers import DDPMScheduler

from lerobot_sdp.geometry import ChunkGeometry
from lerobot_sdp.noise_schemes import (
    SCHEMES,
    NoiseSchemeWeights,
    chunkwise_levels,
    sample_delays,
    sample_levels,
)
from lerobot_sdp.schedule import PerSlotSchedule


def setup(n_inference=100, n_chunks=2):
    g = ChunkGeometry(
        n_obs_steps=2, chunk_len=4, n_chunks=n_chunks, num_inference_steps=n_inference, downsampling=4
    )
    return g, PerSlotSchedule(
        DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2"), n_inference
    )


@pytest.mark.parametrize("name", list(SCHEMES))
def test_levels_stay_in_training_range(name):
    g, sched = setup()
    levels = SCHEMES[name](4096, g, sched)
    assert levels.shape == (4096, g.horizon)
    assert levels.min() >= 0 and levels.max() <= 99


@pytest.mark.parametrize("n_inference, n_chunks", [(100, 2), (10, 2), (16, 4)])
def test_chunkwise_levels_fall_in_each_chunks_band(n_inference, n_chunks):
    g, sched = setup(n_inference, n_chunks)
    s = g.steps_per_call
    levels = chunkwise_levels(2048, g, sched)
    for chunk in range(n_chunks):
        slots = g.slot_chunk == chunk
        band = sched.train_timesteps(torch.arange(chunk * s + 1, (chunk + 1) * s + 1))
        assert torch.isin(levels[:, slots], band).all()
        # one level per chunk, and every level of the band is visited
        assert (levels[:, slots] == levels[:, slots][:, :1]).all()
        assert set(levels[:, slots][:, 0].tolist()) == set(band.tolist())
    # one offset shared by all chunks: chunk 1 sits exactly s inference steps above chunk 0
    k0 = torch.searchsorted(sched.timestep_table, levels[:, g.slot_chunk == 0][:, 0].contiguous())
    k1 = torch.searchsorted(sched.timestep_table, levels[:, g.slot_chunk == 1][:, 0].contiguous())
    assert torch.equal(k1 - k0, torch.full_like(k0, s))


def classify_rows(levels, g, sched):
    """Which scheme produced each row, read off the levels alone (independent of the sampler):
    0 constant, 1 linear, 2 independent, 3 chunkwise."""
    ramp = SCHEMES["linear"](1, g, sched)[0]
    s = g.steps_per_call
    chunkwise = torch.ones(levels.shape[0], dtype=torch.bool)
    for chunk in range(g.n_chunks):
        slots = levels[:, g.slot_chunk == chunk]
        band = sched.train_timesteps(torch.arange(chunk * s + 1, (chunk + 1) * s + 1))
        chunkwise &= (slots == slots[:, :1]).all(dim=1) & torch.isin(slots[:, 0], band)
    kind = torch.full((levels.shape[0],), 2)
    kind[(levels == levels[:, :1]).all(dim=1)] = 0
    kind[(levels == ramp).all(dim=1)] = 1
    kind[chunkwise] = 3
    return kind


def test_mixture_frequencies_match_weights():
    g, sched = setup()
    torch.manual_seed(0)
    weights = NoiseSchemeWeights(constant=0.2, linear=0.1, independent=0.3, chunkwise=0.4)
    scheme = classify_rows(sample_levels(weights, 40_000, g, sched), g, sched)
    freq = torch.bincount(scheme, minlength=4).float() / scheme.numel()
    # binomial standard error at n = 40,000 is at most 0.0025: 4 of them
    torch.testing.assert_close(freq, torch.tensor([0.2, 0.1, 0.3, 0.4]), atol=0.01, rtol=0)


@pytest.mark.parametrize("name", list(SCHEMES))
def test_a_single_scheme_mixture_gives_only_that_scheme(name):
    g, sched = setup()
    weights = NoiseSchemeWeights(**{n: float(n == name) for n in SCHEMES})
    kind = classify_rows(sample_levels(weights, 512, g, sched), g, sched)
    assert (kind == list(SCHEMES).index(name)).all()


def delay_setup(max_delay):
    g = ChunkGeometry(
        n_obs_steps=2, chunk_len=4, n_chunks=2, num_inference_steps=10, downsampling=4, max_delay=max_delay
    )
    return g, PerSlotSchedule(DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2"), 10)


def test_without_max_delay_the_levels_pass_through_without_a_random_draw():
    g, schedule = delay_setup(0)
    levels = sample_levels(NoiseSchemeWeights(), 8, g, schedule)
    state = torch.get_rng_state()
    out, committed = sample_delays(levels, g)
    assert out is levels and committed is None
    assert torch.equal(torch.get_rng_state(), state)  # the paper's training, draw for draw


def test_each_sample_draws_its_delay_and_its_committed_slots_are_clean():
    g, schedule = delay_setup(3)
    torch.manual_seed(0)
    levels = sample_levels(NoiseSchemeWeights(chunkwise=1.0, constant=0.0), 4000, g, schedule)
    delayed, committed = sample_delays(levels, g)
    d = committed.sum(1)
    counts = torch.bincount(d, minlength=4)
    assert len(counts) == 4
    assert (counts > 4000 / 4 * 0.85).all()  # U{0..3}: about 1000 each
    for i in range(50):
        n = int(d[i])
        row = delayed[i].tolist()
        assert row[1 : 1 + n] == [-1] * n  # committed slots: the clean timestep
        assert row[0] == levels[i, 0].item()  # the past slot keeps its level
        assert row[1 + n :] == levels[i, 1 : g.horizon - n].tolist()  # the rest moved n slots later
        assert committed[i].nonzero().flatten().tolist() == list(range(1, 1 + n))
