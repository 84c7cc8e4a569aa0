import pytest
import torch
from diffusers import DDPMScheduler

from lerobot_sdp.geometry import ChunkGeometry
from lerobot_sdp.noise_schemes import SCHEMES, NoiseSchemeWeights, chunkwise_levels, sample_levels
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


def test_mixture_frequencies_match_weights():
    g, sched = setup()
    torch.manual_seed(0)
    weights = NoiseSchemeWeights(constant=0.2, linear=0.1, independent=0.3, chunkwise=0.4)
    _, scheme = sample_levels(weights, 40_000, g, sched)
    freq = torch.bincount(scheme, minlength=4).float() / scheme.numel()
    torch.testing.assert_close(freq, torch.tensor([0.2, 0.1, 0.3, 0.4]), atol=0.01, rtol=0)


def test_mixture_rows_come_from_their_scheme():
    g, sched = setup()
    levels, scheme = sample_levels(NoiseSchemeWeights(constant=0.5, chunkwise=0.5), 512, g, sched)
    constant_rows = levels[scheme == 0]
    assert (constant_rows == constant_rows[:, :1]).all()
    chunk_rows = levels[scheme == 3]
    assert (chunk_rows[:, -1] > chunk_rows[:, 0]).all()


@pytest.mark.parametrize("bad", [dict(constant=-0.1), dict(constant=0.0, chunkwise=0.0)])
def test_bad_weights_are_a_clear_error(bad):
    with pytest.raises(ValueError, match="noise_schemes"):
        NoiseSchemeWeights(**bad)
