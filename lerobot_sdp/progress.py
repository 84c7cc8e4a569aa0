"""Progress bars of our dataset writers, kept readable."""

from collections.abc import Iterator
from contextlib import contextmanager

import datasets


@contextmanager
def without_datasets_progress_bars() -> Iterator[None]:
    """LeRobot's save_episode runs a `datasets` map per episode; its bars would interleave with ours."""
    were_disabled = datasets.are_progress_bars_disabled()
    datasets.disable_progress_bars()
    try:
        yield
    finally:
        if not were_disabled:
            datasets.enable_progress_bars()
