"""`lerobot-sdp-bench animation`: one lerobot-eval video -> a small animated WebP / GIF."""

import numpy as np
import pytest
from lerobot.utils.io_utils import write_video
from PIL import Image

from lerobot_sdp.benchmarks.cli import main


def _eval_folder(root, frames: int = 40, size: int = 96, noise: bool = False):
    """A lerobot-eval output folder whose one episode video shows a white square moving right."""
    rng = np.random.default_rng(0)
    video = root / "videos" / "pusht_0" / "eval_episode_0.mp4"
    video.parent.mkdir(parents=True)
    stack = []
    for i in range(frames):
        frame = (
            rng.integers(0, 255, (size, size, 3), dtype=np.uint8)
            if noise
            else np.zeros((size, size, 3), np.uint8)
        )
        frame[40:56, 2 * i : 2 * i + 16] = 255
        stack.append(frame)
    write_video(video, stack, fps=10)
    return root


def _square_left_edge(image: Image.Image) -> int:
    bright = np.asarray(image.convert("L")) > 128
    return int(np.argmax(bright.any(axis=0)))


@pytest.mark.parametrize("suffix", [".webp", ".gif"])
def test_an_eval_folder_becomes_a_small_animation_of_its_first_episode(tmp_path, suffix):
    out = tmp_path / "docs" / f"rollout{suffix}"
    main(["animation", str(_eval_folder(tmp_path / "eval")), "--output", str(out), "--width", "192"])
    assert out.stat().st_size < 1_000_000
    with Image.open(out) as anim:
        assert anim.format == suffix[1:].upper() and anim.size == (192, 192)
        assert anim.n_frames == 20  # every second frame of 40
        if suffix == ".gif":  # Pillow reads back frame durations of GIFs only
            assert anim.info["duration"] == 200  # 10 fps, one frame in two
        edges = []
        for i in (0, anim.n_frames - 1):
            anim.seek(i)
            edges.append(_square_left_edge(anim))
    # the square starts at x = 0 and its last kept frame (38) is at 76 px of 96, i.e. 152 of 192
    assert edges[0] <= 2 and abs(edges[1] - 152) <= 3


def test_over_the_size_limit_the_frame_rate_then_the_width_drop(tmp_path):
    eval_dir = _eval_folder(tmp_path / "eval", noise=True)
    out = tmp_path / "small.webp"
    main(
        [
            "animation",
            str(eval_dir / "videos/pusht_0/eval_episode_0.mp4"),
            "--output",
            str(out),
            "--max_kb",
            "30",
        ]
    )
    assert out.stat().st_size <= 30_000
    with Image.open(out) as anim:
        assert anim.n_frames < 20  # fewer frames than the default one in two
    with pytest.raises(ValueError, match="raise --max_kb"):
        main(["animation", str(eval_dir), "--output", str(tmp_path / "tiny.webp"), "--max_kb", "1"])


def test_existing_output_is_kept_without_overwrite(tmp_path):
    eval_dir = _eval_folder(tmp_path / "eval", frames=10)
    out = tmp_path / "rollout.webp"
    out.write_bytes(b"mine")
    with pytest.raises(SystemExit, match="--overwrite"):
        main(["animation", str(eval_dir), "--output", str(out)])
    assert out.read_bytes() == b"mine"
    main(["animation", str(eval_dir), "--output", str(out), "--overwrite"])
    assert out.read_bytes()[8:12] == b"WEBP"


def test_a_folder_without_videos_and_a_wrong_suffix_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="No rollout video under"):
        main(["animation", str(tmp_path), "--output", str(tmp_path / "a.webp")])
    with pytest.raises(SystemExit, match=r"must end in \.webp or \.gif"):
        main(["animation", str(tmp_path), "--output", str(tmp_path / "a.png")])
