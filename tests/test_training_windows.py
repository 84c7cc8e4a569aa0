"""Which frames SDP trains on: `drop_n_last_frames` against LeRobot's real EpisodeAwareSampler and
LeRobotDataset windows (issue: SDP used to drop the end of every episode that DP keeps).

Every test reads the windows the way `lerobot-train` builds them (delta timestamps from the config's
delta indices, the sampler from the episode boundaries and `drop_n_last_frames`), on a dataset
whose actions encode (episode, frame), so the executed frames are read off the data itself."""

import pytest
import torch
from lerobot.datasets import EpisodeAwareSampler
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from sdp_test_utils import make_tiny_pusht_dataset, tiny_config

LENGTHS = [9, 13, 22]  # the shortest is barely longer than one chunk of 8


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("windows") / "ds"
    make_tiny_pusht_dataset(root, lengths=LENGTHS)
    return root


def windowed_dataset(root, cfg) -> LeRobotDataset:
    """The dataset as `lerobot-train` builds it for `cfg` (delta timestamps from its delta indices)."""
    meta = LeRobotDataset("local/tiny_pusht", root=root).meta
    return LeRobotDataset("local/tiny_pusht", root=root, delta_timestamps=resolve_delta_timestamps(cfg, meta))


def windows(root, cfg) -> tuple[list[tuple[int, int]], set[tuple[int, int]]]:
    """(episode, current frame) of every sample LeRobot's sampler yields, and every (episode, frame)
    that some sample's executed chunk covers; fails if an executed slot is padding."""
    ds = windowed_dataset(root, cfg)
    sampler = EpisodeAwareSampler(
        ds.meta.episodes["dataset_from_index"],
        ds.meta.episodes["dataset_to_index"],
        drop_n_last_frames=cfg.drop_n_last_frames,
    )
    starts, covered = [], set()
    for idx in sampler:
        item = ds[idx]
        episode, frame = int(item["episode_index"]), int(item["frame_index"])
        starts.append((episode, frame))
        pad = item["action_is_pad"][cfg.geometry.executed]
        assert not pad.any(), f"executed chunk of ({episode}, {frame}) runs past the episode end"
        # slot To-1 holds the current frame's action: the executed chunk is frame .. frame + Tb - 1
        covered |= {(episode, frame + i) for i in range(cfg.n_action_steps)}
    return starts, covered


@pytest.mark.parametrize("n_chunks", [1, 2, 4])
@pytest.mark.parametrize("n_obs_steps", [1, 2, 3])
def test_every_frame_is_executed_and_dp_frames_are_kept(dataset_root, n_chunks, n_obs_steps):
    cfg = tiny_config(n_obs_steps=n_obs_steps, n_action_steps=8, n_chunks=n_chunks, num_inference_steps=16)
    starts, covered = windows(dataset_root, cfg)
    every_frame = {(ep, f) for ep, length in enumerate(LENGTHS) for f in range(length)}
    assert covered == every_frame, f"never executed: {sorted(every_frame - covered)[:10]}"
    # LeRobot's Diffusion Policy with the same chunk keeps these start frames: SDP keeps them all.
    dp = DiffusionConfig(n_obs_steps=n_obs_steps, n_action_steps=8)
    dp_starts = {(ep, f) for ep, length in enumerate(LENGTHS) for f in range(length - dp.drop_n_last_frames)}
    assert dp_starts <= set(starts), f"dropped frames DP keeps: {sorted(dp_starts - set(starts))[:10]}"


def test_later_chunks_may_run_past_the_end_and_are_marked_padded(dataset_root):
    """Keeping the last start frames means the chunks after the executed one reach past the episode:
    LeRobot copy-pads them and flags them in `action_is_pad`, which is what the loss can mask."""
    cfg = tiny_config(n_obs_steps=2, n_action_steps=8, n_chunks=2, num_inference_steps=16)
    ds = windowed_dataset(dataset_root, cfg)
    last_start = LENGTHS[0] - cfg.n_action_steps  # first episode, last frame the sampler keeps
    item = ds[last_start]
    pad = item["action_is_pad"]
    g = cfg.geometry
    assert not pad[: g.executed.stop].any()
    assert pad[g.executed.stop :].all()
    torch.testing.assert_close(
        item["action"][g.executed.stop :],
        item["action"][g.executed.stop - 1].expand(g.horizon - g.executed.stop, -1),
    )
