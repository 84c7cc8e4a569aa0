"""LeRobot's torchcodec fallback (no FFmpeg shared libraries) shows as one line, not ~110 of traceback."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_sdp import torchcodec_notice
from lerobot_sdp.torchcodec_notice import NO_FFMPEG, TorchcodecFallbackFilter, one_line

BIN = Path(sys.executable).parent


def torchcodec_message(errors: dict[int, str]) -> str:
    """LeRobot's warning text around torchcodec's RuntimeError, as get_safe_default_video_backend logs it."""
    sections = "\n".join(
        f'FFmpeg version {v}:\nTraceback (most recent call last):\n  File "x.py", line 1\n{err}\n\n'
        "The above exception was the direct cause of the following exception:\n\n"
        "Traceback (most recent call last):\n"
        f"OSError: Could not load this library: libtorchcodec_core{v}.so\n"
        for v, err in errors.items()
    )
    return (
        "Could not load libtorchcodec. Likely causes:\n  1. FFmpeg is not properly installed\n"
        f"[start of libtorchcodec loading traceback]\n{sections}[end of libtorchcodec loading traceback].\n"
        "'torchcodec' is installed but cannot be loaded (see the error above). "
        "Falling back to 'pyav' as a default decoder."
    )


NO_FFMPEG_MESSAGE = torchcodec_message(
    {
        v: f"OSError: libavutil.so.{v + 52}: cannot open shared object file: No such file or directory"
        for v in (8, 7, 6, 5, 4)
    }
)


def test_no_ffmpeg_collapses_to_the_no_ffmpeg_line():
    assert one_line(NO_FFMPEG_MESSAGE) == NO_FFMPEG


def test_installed_ffmpeg_that_fails_names_its_error():
    errors = {v: f"OSError: libavutil.so.{v + 52}: cannot open shared object file" for v in (8, 7, 5, 4)}
    errors[6] = "OSError: libtorchcodec_core6.so: undefined symbol: _ZN3c10foo"
    line = one_line(torchcodec_message(dict(sorted(errors.items(), reverse=True))))
    assert "\n" not in line and "undefined symbol: _ZN3c10foo" in line and "PyAV" in line
    assert "SDP_TORCHCODEC_DETAILS=1" in line


def test_filter_rewrites_once_drops_repeats_and_passes_other_messages():
    logger = logging.getLogger("test_torchcodec_notice")
    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep()
    logger.addHandler(handler)
    logger.addFilter(fallback := TorchcodecFallbackFilter())
    logger.propagate = False
    try:
        logger.warning(NO_FFMPEG_MESSAGE)
        logger.warning("something else")
        logger.warning(NO_FFMPEG_MESSAGE)
    finally:
        logger.removeHandler(handler)
        logger.removeFilter(fallback)
    assert records == [NO_FFMPEG, "something else"]


def test_install_is_idempotent_and_details_env_turns_it_off(monkeypatch):
    logger = logging.getLogger(torchcodec_notice.LOGGER)
    monkeypatch.setattr(logger, "filters", [])
    torchcodec_notice.install()
    torchcodec_notice.install()
    assert sum(isinstance(f, TorchcodecFallbackFilter) for f in logger.filters) == 1
    monkeypatch.setattr(logger, "filters", [])
    monkeypatch.setenv(torchcodec_notice.DETAILS_ENV, "1")
    torchcodec_notice.install()
    assert logger.filters == []


def torchcodec_loads() -> bool:
    code = "import torchcodec"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120).returncode == 0


@pytest.mark.parametrize("details", [False, True], ids=["default", "SDP_TORCHCODEC_DETAILS"])
def test_lerobot_train_help_shows_no_torchcodec_traceback(details):
    """`lerobot-train --help` builds a DatasetConfig, whose default video backend probes torchcodec after
    LeRobot imported the plugin: the console shows one line about it (or nothing when it loads)."""
    env = {k: v for k, v in os.environ.items() if k != torchcodec_notice.DETAILS_ENV}
    env |= {"HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    if details:
        if torchcodec_loads():
            pytest.skip("torchcodec loads on this machine: there is no fallback message to show")
        env[torchcodec_notice.DETAILS_ENV] = "1"
    proc = subprocess.run(
        [str(BIN / "lerobot-train"), "--help"], capture_output=True, text=True, timeout=300, env=env
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-3000:]
    assert "usage: lerobot-train" in output
    if details:  # the switch really shows LeRobot's message: the default run's check is not vacuous
        assert "libtorchcodec loading traceback" in output
        return
    assert "Traceback" not in output, output[:3000]
    assert "libtorchcodec" not in output
    fallback_lines = [line for line in output.splitlines() if "PyAV instead" in line]
    assert len(fallback_lines) == (0 if torchcodec_loads() else 1), fallback_lines
