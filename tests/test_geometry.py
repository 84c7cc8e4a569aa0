import pytest
import torch

from lerobot_sdp.geometry import ChunkGeometry


def geo(**kw):
    base = dict(n_obs_steps=2, chunk_len=8, n_chunks=2, num_inference_steps=100, downsampling=4)
    return ChunkGeometry(**{**base, **kw})


def test_authors_state_pusht_geometry():
    g = geo()  # To=2, Tb=8, h=2, U-Net with 3 levels: the authors' horizon 20
    assert (g.horizon, g.n_past, g.n_pad, g.steps_per_call) == (20, 1, 3, 50)
    assert g.executed == slice(1, 9)
    assert g.slot_chunk.tolist() == [0] * 9 + [1] * 11
    assert g.start_levels.tolist() == [50] * 9 + [100] * 11


def test_start_levels_are_the_paper_staircase():
    g = geo(n_chunks=4, chunk_len=5, num_inference_steps=16, n_obs_steps=1, downsampling=1)
    assert g.horizon == 20 and g.n_pad == 0
    assert g.start_levels.view(4, 5)[:, 0].tolist() == [4, 8, 12, 16]  # [N/h, 2N/h, ..., N]


def test_plain_dp_is_one_chunk():
    g = geo(n_chunks=1)
    assert g.steps_per_call == 100 and torch.all(g.start_levels == 100)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(num_inference_steps=100, n_chunks=3), "not divisible by n_chunks=3"),
        (dict(chunk_len=0), "n_action_steps"),
        (dict(n_chunks=-1), "n_chunks"),
        (dict(n_obs_steps=0), "n_obs_steps"),
    ],
)
def test_impossible_geometry_names_the_value_to_change(kw, match):
    with pytest.raises(ValueError, match=match):
        geo(**kw)


def test_committed_slots_sit_after_the_past_and_push_the_chunks_later():
    """docs/deployment.md's layout table: To=2, Tb=4, h=2, N=10 (s=5), room for 3 committed slots."""
    g = geo(chunk_len=4, num_inference_steps=10, max_delay=3)
    assert (g.horizon, g.n_pad) == (12, 3)
    layouts = {
        0: [5, 5, 5, 5, 5, 10, 10, 10, 10, 10, 10, 10],
        1: [5, 0, 5, 5, 5, 5, 10, 10, 10, 10, 10, 10],
        2: [5, 0, 0, 5, 5, 5, 5, 10, 10, 10, 10, 10],
        3: [5, 0, 0, 0, 5, 5, 5, 5, 10, 10, 10, 10],
    }
    delays = torch.tensor(list(layouts))
    start = g.start_levels.expand(len(layouts), -1)
    assert g.delayed(start, delays, clean=0).tolist() == list(layouts.values())
    assert g.committed_mask(delays).sum(1).tolist() == [0, 1, 2, 3]
    assert g.committed_mask(delays)[2].nonzero().flatten().tolist() == [1, 2]


def test_room_for_committed_slots_grows_the_horizon_only_past_the_padding():
    base = dict(chunk_len=8, n_chunks=4, num_inference_steps=16)
    assert geo(**base).horizon == 36  # 1 + 32 + 3 padding
    assert geo(**base, max_delay=3).horizon == 36  # the padding holds 3 committed slots
    assert geo(**base, max_delay=4).horizon == 40
    assert "room for 4 committed" in geo(**base, max_delay=4).describe()


@pytest.mark.parametrize("max_delay", [-1, 8])
def test_max_delay_beyond_the_executed_chunk_is_refused(max_delay):
    with pytest.raises(ValueError, match=r"`max_delay` must be between 0 and .* = 7"):
        geo(max_delay=max_delay)
