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
    0 constant, 1 linear, 2 independent, 3 chunkwise, 4 independent_chunks. An independent_chunks
    row whose chunks drew one level, or a chunk-wise staircase, reads as that scheme (about 1.5 %
    of them here)."""
    ramp = SCHEMES["linear"](1, g, sched)[0]
    s = g.steps_per_call
    chunkwise = torch.ones(levels.shape[0], dtype=torch.bool)
    first = sched.train_timesteps(torch.arange(1, s + 1))  # chunk 0's band
    for chunk in range(g.n_chunks):
        slots = levels[:, g.slot_chunk == chunk]
        band = sched.train_timesteps(torch.arange(chunk * s + 1, (chunk + 1) * s + 1))
        # the same offset in every chunk's band: chunk i's level is chunk 0's moved by i * s steps
        same_offset = band[
            torch.searchsorted(first, levels[:, g.slot_chunk == 0][:, 0].contiguous()).clamp(max=s - 1)
        ]
        chunkwise &= (slots == slots[:, :1]).all(dim=1) & (slots[:, 0] == same_offset)
    per_chunk = torch.ones(levels.shape[0], dtype=torch.bool)
    for chunk in range(g.n_chunks):
        slots = levels[:, g.slot_chunk == chunk]
        per_chunk &= (slots == slots[:, :1]).all(dim=1)
    kind = torch.full((levels.shape[0],), 2)
    kind[per_chunk] = 4
    kind[(levels == levels[:, :1]).all(dim=1)] = 0
    kind[(levels == ramp).all(dim=1)] = 1
    kind[chunkwise] = 3
    return kind


def test_mixture_frequencies_match_weights():
    g, sched = setup()
    torch.manual_seed(0)
    weights = NoiseSchemeWeights(
        constant=0.2, linear=0.1, independent=0.2, chunkwise=0.3, independent_chunks=0.2
    )
    scheme = classify_rows(sample_levels(weights, 40_000, g, sched), g, sched)
    freq = torch.bincount(scheme, minlength=5).float() / scheme.numel()
    # binomial standard error at n = 40,000 is at most 0.0025: 4 of them
    torch.testing.assert_close(freq, torch.tensor([0.2, 0.1, 0.2, 0.3, 0.2]), atol=0.01, rtol=0)


@pytest.mark.parametrize("name", list(SCHEMES))
def test_a_single_scheme_mixture_gives_only_that_scheme(name):
    g, sched = setup()
    torch.manual_seed(0)
    weights = NoiseSchemeWeights(**{n: float(n == name) for n in SCHEMES})
    kind = classify_rows(sample_levels(weights, 512, g, sched), g, sched)
    # independent_chunks: the few rows that read as another scheme (see classify_rows)
    share = 0.95 if name == "independent_chunks" else 1.0
    assert (kind == list(SCHEMES).index(name)).float().mean() >= share


@pytest.mark.parametrize("n_chunks", [2, 4])
def test_independent_chunks_draw_one_level_per_chunk_independently_over_the_whole_table(n_chunks):
    g, sched = setup(16, n_chunks)
    torch.manual_seed(0)
    levels = SCHEMES["independent_chunks"](20_000, g, sched)
    firsts = []
    for chunk in range(n_chunks):
        slots = levels[:, g.slot_chunk == chunk]
        assert (slots == slots[:, :1]).all()  # one level for every slot of the chunk
        firsts.append(slots[:, 0])
        assert set(slots[:, 0].tolist()) == set(range(100))  # every training timestep, not a grid
    later, earlier = firsts[1].float(), firsts[0].float()
    # independent: the later chunk is cleaner than the earlier about as often as noisier
    assert abs((later < earlier).float().mean().item() - (later > earlier).float().mean().item()) < 0.03
    assert abs(torch.corrcoef(torch.stack([later, earlier]))[0, 1].item()) < 0.03
    assert abs(earlier.mean().item() - 49.5) < 1.0  # U{0..99}'s mean, within 5 standard errors


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
