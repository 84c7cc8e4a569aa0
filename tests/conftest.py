"""Shared test fixtures. The rootdir conftest keeps tests importable without a `tests` package
(site-packages already has one, from draccus)."""

import logging
from pathlib import Path

import pytest


def real_pusht_zarr() -> Path | None:
    """The real Push-T demonstrations, found as the main job finds them: $SDP_PUSHT_ZARR, then
    ../shared/data/pusht/ beside the repository; None when neither exists."""
    from lerobot_sdp.pusht.data import NoPushTDataError, find_zarr

    try:
        return find_zarr(None)
    except NoPushTDataError:  # $SDP_PUSHT_ZARR names a path that does not exist
        return None


@pytest.fixture
def pusht_zarr() -> Path:
    path = real_pusht_zarr()
    if path is None:
        pytest.skip("real Push-T zarr not found: set SDP_PUSHT_ZARR or put it at ../shared/data/pusht/")
    return path


@pytest.fixture(autouse=True)
def _restore_root_logging():
    """CLIs run in-process (`init_logging`, `basicConfig`) attach handlers to the sys.stderr that pytest
    swaps per test; left in place they write to a closed stream in later tests. Undo them after each test."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.fixture
def server_mod(tmp_path, monkeypatch):
    """The module, imported with the working directory in tmp (LeRobot's server logger makes `logs/`)."""
    monkeypatch.chdir(tmp_path)
    from lerobot_sdp import policy_server

    return policy_server
