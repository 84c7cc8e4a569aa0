"""What our LeRobotDataset writers (the Push-T and robomimic converters, the Lift recorder) share:
a safe output directory and readable progress bars."""

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import datasets


def clear_output_dir(out_dir: Path, overwrite: bool) -> None:
    """Make room for LeRobotDataset.create, which needs `out_dir` absent.

    An existing `out_dir` is deleted only with `overwrite`, and only if it is something a writer could
    have made: a LeRobot dataset or an empty directory. Raises FileExistsError otherwise."""
    out_dir = Path(out_dir)
    if not out_dir.exists():
        return
    if not overwrite:
        raise FileExistsError(
            f"{out_dir} already exists; pass --overwrite to replace it, or pick another directory"
        )
    is_dataset = (out_dir / "meta" / "info.json").is_file()
    if not out_dir.is_dir() or not (is_dataset or not any(out_dir.iterdir())):
        raise FileExistsError(
            f"{out_dir} is not a LeRobot dataset: refusing to delete it with --overwrite; "
            "pick another directory"
        )
    shutil.rmtree(out_dir)


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
