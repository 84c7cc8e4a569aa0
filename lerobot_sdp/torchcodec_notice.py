"""One line instead of LeRobot's ~110-line torchcodec traceback on machines without FFmpeg.

LeRobot picks its default video decoder by importing torchcodec (`get_safe_default_video_backend`,
run whenever a `DatasetConfig` or `LeRobotDataset` is built, `lerobot-train --help` included). When
FFmpeg's shared libraries are missing, torchcodec's import fails after trying FFmpeg 8, 7, 6, 5 and 4,
and LeRobot logs the whole error, five tracebacks, as a WARNING, then falls back to PyAV, which works.
The console then looks like a crash, and real errors scroll away.

`install()` (run when `lerobot_sdp` is imported: by LeRobot's plugin discovery at the start of
`lerobot-train` / `lerobot-eval`, and by our own `lerobot-sdp-*` commands) puts a filter on that one
logger which rewrites that one message to a single line, once per process. Every other message passes
unchanged. `SDP_TORCHCODEC_DETAILS=1` turns the filter off to see LeRobot's full message.
"""

import logging
import os
import re

LOGGER = "lerobot.utils.import_utils"
DETAILS_ENV = "SDP_TORCHCODEC_DETAILS"
NO_FFMPEG = (
    "torchcodec: no FFmpeg shared libraries found, LeRobot decodes videos with PyAV instead; "
    "install FFmpeg (4 to 8, shared libraries) to use torchcodec."
)
_MISSING_FFMPEG_LIB = re.compile(r"lib(?:av\w+|sw\w+|postproc)\.so[.\d]*: cannot open shared object file")


def _is_torchcodec_fallback(message: str) -> bool:
    return "Could not load libtorchcodec" in message and "Falling back to 'pyav'" in message


def one_line(message: str) -> str:
    """The single line that replaces LeRobot's torchcodec fallback message."""
    # torchcodec's message has one "FFmpeg version N:" section per version it tried.
    per_version = re.split(r"^FFmpeg version \d+:$", message, flags=re.MULTILINE)[1:]
    if per_version and all(_MISSING_FFMPEG_LIB.search(section) for section in per_version):
        return NO_FFMPEG
    # An FFmpeg was found but torchcodec still fails (e.g. a torch it was not built for): name the error
    # for that FFmpeg, the first one that is neither a missing FFmpeg library nor torch's wrapper.
    errors = [line.strip() for line in message.splitlines() if re.match(r"\s*\w*(Error|Exception):", line)]
    relevant = [
        e for e in errors if not _MISSING_FFMPEG_LIB.search(e) and "Could not load this library" not in e
    ]
    cause = f" ({(relevant or errors)[0]})" if errors else ""
    return (
        f"torchcodec cannot be loaded{cause}; LeRobot decodes videos with PyAV instead. "
        f"Set {DETAILS_ENV}=1 for the full error."
    )


class TorchcodecFallbackFilter(logging.Filter):
    """Collapses LeRobot's torchcodec fallback warning to one line and drops its repeats."""

    def __init__(self) -> None:
        super().__init__()
        self.shown = False

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if not _is_torchcodec_fallback(message):
            return True
        if self.shown:
            return False
        self.shown = True
        record.msg, record.args = one_line(message), ()
        record.exc_info = record.exc_text = None
        return True


def install() -> None:
    """Idempotent; a no-op when SDP_TORCHCODEC_DETAILS is set."""
    if os.environ.get(DETAILS_ENV, "").lower() in ("1", "true", "yes", "on"):
        return
    logger = logging.getLogger(LOGGER)
    if not any(isinstance(f, TorchcodecFallbackFilter) for f in logger.filters):
        logger.addFilter(TorchcodecFallbackFilter())
