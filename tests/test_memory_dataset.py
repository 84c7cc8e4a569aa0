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
TASKS = ["push the T", "push the T again", "push the T"]
LEROBOT_GET_ITEM = DatasetReader.get_item.__wrapped__  # LeRobot's own reader, under the plugin's


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("memory") / "ds"
    make_tiny_pusht_dataset(root, lengths=LENGTHS, seed=3, tasks=TASKS)
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


@pytest.mark.parametrize("episodes", [None, [0, 2]])
def test_a_batch_gathered_at_once_equals_lerobots_reader_sample_for_sample(dataset_root, episodes):
    ds = windowed(dataset_root, episodes=episodes, n_chunks=5)
    reader = ds._ensure_reader()
    order = torch.randperm(len(ds), generator=torch.Generator().manual_seed(0)).tolist()
    for first in range(0, len(order), 7):
        indices = order[first : first + 7]
        for idx, sample in zip(indices, ds.__getitems__(indices), strict=True):
            assert_same_sample(sample, LEROBOT_GET_ITEM(reader, idx), idx)


def test_the_dataloader_takes_a_batch_at_once_and_collates_lerobots_samples(dataset_root, monkeypatch):
    ds = windowed(dataset_root)
    calls = []
    monkeypatch.setattr(memory_dataset.MemoryTable, "items", spy(memory_dataset.MemoryTable.items, calls))
    indices = [0, 5, len(ds) - 1, 12]
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4, sampler=indices)))
    assert [len(c) for c in calls] == [4]  # one gather for the batch
    lerobots = torch.utils.data.default_collate([LEROBOT_GET_ITEM(ds._ensure_reader(), i) for i in indices])
    assert_same_sample(batch, lerobots, "batch")


def test_a_dataset_lerobot_reads_is_read_per_sample_by_lerobots_reader(dataset_root):
    ds = windowed(dataset_root)
    memory_dataset.read_with_lerobot(ds)
    reader = ds._ensure_reader()
    for idx, sample in zip([3, 0], ds.__getitems__([3, 0]), strict=True):
        assert_same_sample(sample, LEROBOT_GET_ITEM(reader, idx), idx)
    assert memory_dataset.table_of(reader) is None


def spy(method, calls: list):
    def wrapper(self, indices):
        calls.append(list(indices))
        return method(self, indices)

    return wrapper


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
    monkeypatch.delattr(LeRobotDataset, "__getitems__")
    monkeypatch.setenv(memory_dataset.ENV, "0")
    memory_dataset.install()
    assert DatasetReader.get_item is LEROBOT_GET_ITEM
    assert not hasattr(LeRobotDataset, "__getitems__")  # the DataLoader reads sample by sample
    monkeypatch.delenv(memory_dataset.ENV)
    memory_dataset.install()
    assert DatasetReader.get_item.__wrapped__ is LEROBOT_GET_ITEM
    assert LeRobotDataset.__getitems__ is memory_dataset.get_items
