"""Training windows served from memory for low-dimensional LeRobot datasets.

LeRobot 0.6.1's `DatasetReader.get_item` reads every sample through `datasets`: the frame's row, then
one Arrow query per windowed key (`delta_timestamps`), each of which builds a `datasets.Column` and
deep-copies the dataset's features. A Push-T keypoints sample (2 observation frames, 36 actions)
costs about 3.3 ms that way, 210 ms of CPU per batch of 64: as much as the U-Net's update on a small
CPU, which is why the CPU configs needed DataLoader workers holding a core of their own.

A dataset without cameras (every feature a number or a vector) fits in memory many times over: Push-T
keypoints is 25,650 frames of 38 numbers, 4 MB. For such a dataset the reader below builds the table
once, as one tensor per column, and serves a whole batch by indexing those tensors once
(`LeRobotDataset.__getitems__`, which the DataLoader calls with the batch's indices): the frames' rows,
each windowed key at LeRobot's clamped indices, LeRobot's padding masks and task strings. The values,
dtypes, shapes and keys are LeRobot's, sample for sample (tests/test_memory_dataset.py compares every
index of a small dataset, episode ends included). A Push-T batch of 64 costs about 1 ms, collated;
no worker process is needed and both cores go to the update (docs/benchmarks.md, "Training at the
hardware's limit").

`install()` runs when `lerobot_sdp` is imported, so by LeRobot's plugin discovery at the start of
`lerobot-train` and `lerobot-eval`, for every policy type (LeRobot's `diffusion` reads through it
too). Datasets with cameras, or columns that are not numbers, keep LeRobot's reader, with a one-line
notice. `SDP_DATA_IN_MEMORY=0` turns it off: LeRobot's reader for every dataset.
"""

import functools
import logging
import os

import numpy as np
import torch

ENV = "SDP_DATA_IN_MEMORY"
MAX_BYTES = 4 * 2**30  # a table larger than this stays on disk, read by LeRobot's reader
logger = logging.getLogger(__name__)


class MemoryTable:
    """The reader's whole table as tensors, and LeRobot's window lookup on them."""

    def __init__(self, reader, columns: dict[str, torch.Tensor]):
        self.columns = columns
        self.task_names = reader._meta.tasks.index.tolist()  # by task_index; pandas' iloc costs per sample
        episodes = reader._meta.episodes
        ids = torch.as_tensor(episodes["episode_index"], dtype=torch.long)
        self.ep_start = torch.zeros(int(ids.max()) + 1, dtype=torch.long)
        self.ep_end = torch.zeros_like(self.ep_start)
        self.ep_start[ids] = torch.as_tensor(episodes["dataset_from_index"], dtype=torch.long)
        self.ep_end[ids] = torch.as_tensor(episodes["dataset_to_index"], dtype=torch.long)
        deltas = reader.delta_indices or {}
        self.deltas = {key: torch.as_tensor(delta, dtype=torch.long) for key, delta in deltas.items()}
        # Rows are absolute frame indices, unless the reader holds a subset of the episodes.
        self.row_of = None
        if reader._absolute_to_relative_idx is not None:
            absolute = columns["index"]
            self.row_of = torch.full((int(absolute.max()) + 1,), -1, dtype=torch.long)
            self.row_of[absolute] = torch.arange(len(absolute))

    def item(self, idx: int) -> dict:
        return self.items([idx])[0]

    def items(self, indices) -> list[dict]:
        """The samples at `indices`, gathered for all of them at once: LeRobot's window of each
        windowed key (the frame plus its deltas, clamped to the episode) and its padding mask."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        batch = {key: column[idx] for key, column in self.columns.items()}
        frame = batch["index"].unsqueeze(1)
        start = self.ep_start[batch["episode_index"]].unsqueeze(1)
        end = self.ep_end[batch["episode_index"]].unsqueeze(1)
        padding = {}
        for key, delta in self.deltas.items():
            wanted = frame + delta
            padding[f"{key}_is_pad"] = (wanted < start) | (wanted >= end)
            rows = wanted.clamp(start, end - 1)
            batch[key] = self.columns[key][rows if self.row_of is None else self.row_of[rows]]
        batch.update(padding)
        keys = list(batch)
        tasks = [self.task_names[t] for t in batch["task_index"].tolist()]
        # one sample per row, as views of the gathered tensors: the DataLoader's collate stacks them
        rows = zip(*(batch[key].unbind(0) for key in keys), strict=True)
        samples = [dict(zip(keys, row, strict=True)) for row in rows]
        return [sample | {"task": task} for sample, task in zip(samples, tasks, strict=True)]


def why_not_in_memory(reader) -> str | None:
    """Why this reader's dataset cannot be served from memory, or None when it can."""
    meta = reader._meta
    if meta.camera_keys:
        return f"it has cameras ({', '.join(meta.camera_keys)})"
    features = reader.hf_dataset.features
    for key, feature in features.items():
        dtype = getattr(feature, "dtype", None) or getattr(getattr(feature, "feature", None), "dtype", None)
        if dtype not in ("float32", "float64", "int64", "int32", "bool", "int8", "int16", "uint8"):
            return f"its column {key!r} is not numeric ({feature})"
    size = reader.hf_dataset.data.nbytes
    if size > MAX_BYTES:
        return f"its table ({size / 2**30:.1f} GiB) is larger than {MAX_BYTES / 2**30:.0f} GiB"
    return None


def build_table(reader) -> MemoryTable | None:
    """The reader's table in memory, or None (with a one-line notice) where LeRobot's reader stays."""
    name = reader._meta.repo_id
    reason = why_not_in_memory(reader)
    if reason is not None:
        logger.info("Dataset %s is read by LeRobot's reader: %s.", name, reason)
        return None
    numpy_columns = reader.hf_dataset.with_format("numpy")[:]
    ragged = [key for key, v in numpy_columns.items() if v.dtype == object]
    if ragged:  # lists of varying length: no single tensor holds them
        logger.info("Dataset %s is read by LeRobot's reader: column %r varies in length.", name, ragged[0])
        return None
    columns = {key: torch.from_numpy(np.ascontiguousarray(v)) for key, v in numpy_columns.items()}
    table = MemoryTable(reader, columns)
    size = sum(c.nbytes for c in columns.values())
    logger.info(
        "Dataset %s served from memory (%d frames, %.1f MB; %s=0 reads it with LeRobot's reader).",
        name, len(reader.hf_dataset), size / 1e6, ENV,
    )  # fmt: skip
    return table


def read_with_lerobot(dataset) -> None:
    """Let LeRobot's own reader serve this dataset (a benchmark's A/B against the table)."""
    dataset._ensure_reader().lerobot_reads = True


def table_of(reader) -> MemoryTable | None:
    """The reader's in-memory table, built on first use and again if the reader reloads its data."""
    if getattr(reader, "lerobot_reads", False):
        return None
    cached = getattr(reader, "_sdp_memory_table", None)
    if cached is None or cached[0] is not reader.hf_dataset:
        cached = (reader.hf_dataset, build_table(reader))
        reader._sdp_memory_table = cached
    return cached[1]


def install() -> None:
    """Serve low-dimensional datasets from memory in this process (module docstring). Idempotent."""
    if os.environ.get(ENV, "1") == "0":
        return
    from lerobot.datasets.dataset_reader import DatasetReader
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    original = DatasetReader.get_item
    if getattr(original, "serves_from_memory", False):
        return

    @functools.wraps(original)
    def get_item(self, idx) -> dict:
        table = table_of(self)
        return original(self, idx) if table is None else table.item(idx)

    get_item.serves_from_memory = True
    DatasetReader.get_item = get_item
    LeRobotDataset.__getitems__ = get_items


def get_items(dataset, indices: list[int]) -> list[dict]:
    """`LeRobotDataset.__getitems__`, which the DataLoader calls with a whole batch of indices: one
    gather from the table for the batch instead of one per sample, or LeRobot's reader per sample."""
    reader = dataset._ensure_reader()
    recording = dataset.writer is not None and not dataset._is_finalized  # __getitem__ says why not
    table = None if recording or reader.hf_dataset is None else table_of(reader)
    return [dataset[i] for i in indices] if table is None else table.items(indices)
