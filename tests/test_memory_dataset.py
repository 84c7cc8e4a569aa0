"""Training windows served from memory (`lerobot_sdp.memory_dataset`) against LeRobot's own reader.

Every sample of a small dataset, read the way `lerobot-train` reads it for SDP (observation history
before an episode's start, an action horizon running past its end), must be LeRobot's: the same keys,
dtypes, shapes, values, padding masks and task string."""

import logging

import pytest
import torch
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from sdp_test_utils import make_tiny_pusht_dataset, tiny_config

from lerobot_sdp import memory_dataset

LENGTHS = [9, 13, 22]  # the shortest is shorter than the action horizon
LEROBOT_GET_ITEM = DatasetReader.get_item.__wrapped__  # LeRobot's own reader, under the plugin's


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("memory") / "ds"
    make_tiny_pusht_dataset(root, lengths=LENGTHS, seed=3)
    return root


def windowed(root, episodes=None, **overrides) -> LeRobotDataset:
    cfg = tiny_config(**overrides)
    meta = LeRobotDataset("local/tiny_pusht", root=root).meta
    delta = resolve_delta_timestamps(cfg, meta)
    return LeRobotDataset("local/tiny_pusht", root=root, episodes=episodes, delta_timestamps=delta)


def assert_same_sample(ours: dict, lerobot: dict, idx: int) -> None:
    assert set(ours) == set(lerobot), idx
    for key, value in lerobot.items():
        if isinstance(value, torch.Tensor):
            assert ours[key].dtype == value.dtype, (idx, key)
            assert ours[key].shape == value.shape, (idx, key)
            assert torch.equal(ours[key], value), (idx, key)
        else:
            assert ours[key] == value, (idx, key)


def test_the_plugin_serves_the_dataset_from_memory(dataset_root):
    ds = windowed(dataset_root)
    ds[0]
    assert memory_dataset.table_of(ds._ensure_reader()) is not None


@pytest.mark.parametrize("overrides", [{}, {"n_obs_steps": 3, "n_chunks": 5}])
def test_every_sample_equals_lerobots_reader(dataset_root, overrides):
    ds = windowed(dataset_root, **overrides)
    reader = ds._ensure_reader()
    table = memory_dataset.build_table(reader)
    pads = torch.stack([table.item(i)["action_is_pad"] for i in range(len(ds))])
    assert pads.any() and not pads.all()  # the windows do run past the episodes' ends
    for idx in range(len(ds)):
        assert_same_sample(table.item(idx), LEROBOT_GET_ITEM(reader, idx), idx)
        assert_same_sample(ds[idx], LEROBOT_GET_ITEM(reader, idx), idx)


def test_a_subset_of_episodes_reads_its_own_rows(dataset_root):
    ds = windowed(dataset_root, episodes=[0, 2])
    reader = ds._ensure_reader()
    table = memory_dataset.build_table(reader)
    assert len(ds) == LENGTHS[0] + LENGTHS[2]
    assert table.row_of is not None
    for idx in range(len(ds)):
        assert_same_sample(table.item(idx), LEROBOT_GET_ITEM(reader, idx), idx)


def test_a_dataset_with_cameras_keeps_lerobots_reader_with_a_notice(tmp_path, caplog):
    root = tmp_path / "img"
    make_tiny_pusht_dataset(root, image=True, n_episodes=1, length=10)
    ds = windowed(root, image=True)
    with caplog.at_level(logging.INFO, logger=memory_dataset.__name__):
        item = ds[3]
    assert memory_dataset.table_of(ds._ensure_reader()) is None
    notices = [r.getMessage() for r in caplog.records if r.name == memory_dataset.__name__]
    assert len(notices) == 1 and "LeRobot's reader: it has cameras (observation.image)" in notices[0]
    assert item["observation.image"].shape[-2:] == (96, 96)


def test_the_environment_variable_turns_it_off(monkeypatch):
    monkeypatch.setattr(DatasetReader, "get_item", LEROBOT_GET_ITEM)
    monkeypatch.setenv(memory_dataset.ENV, "0")
    memory_dataset.install()
    assert DatasetReader.get_item is LEROBOT_GET_ITEM
    monkeypatch.delenv(memory_dataset.ENV)
    memory_dataset.install()
    assert DatasetReader.get_item.__wrapped__ is LEROBOT_GET_ITEM
