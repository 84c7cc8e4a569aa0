"""Turn one lerobot-eval rollout video into a small animated WebP or GIF (e.g. for a README).

`VIDEO` is an mp4 that `lerobot-eval` wrote, or an evaluation's output folder: then its first episode
video (`videos/*/eval_episode_0.mp4`, else the first mp4 under `videos/`). Frames are taken every
`--every` frames and scaled to `--width` pixels; while the file is over `--max_kb`, the frame rate
and then the width are halved, and if it still does not fit the command fails, naming the flags.
The format follows the output's suffix (`.webp` or `.gif`); an existing file is kept unless
`--overwrite`.

    lerobot-sdp-bench animation outputs/mainjob/out/eval --output docs/rollout.webp
"""

import argparse
import io
import logging
from pathlib import Path

import av
from PIL import Image

FORMATS = {".webp": "WEBP", ".gif": "GIF"}


def episode_video(path: Path) -> Path:
    """The mp4 itself, or the first episode video of a lerobot-eval output folder."""
    if path.is_file():
        return path
    videos = sorted(path.glob("videos/*/eval_episode_0.mp4")) or sorted(path.glob("videos/**/*.mp4"))
    if not videos:
        raise FileNotFoundError(
            f"No rollout video under {path}/videos/: pass an mp4, or the --output_dir of a lerobot-eval run "
            "(it records its first 10 episodes)."
        )
    return videos[0]


def read_frames(video: Path) -> tuple[list[Image.Image], float]:
    """Every frame of the video as RGB images, and its frame rate."""
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        fps = float(stream.average_rate or 10)
        frames = [frame.to_image() for frame in container.decode(stream)]
    if not frames:
        raise ValueError(f"{video} holds no video frames.")
    return frames, fps


def encode(frames: list[Image.Image], fps: float, width: int, suffix: str) -> bytes:
    """The frames scaled to ``width`` pixels, as one looping animation at ``fps``."""
    height = max(1, round(frames[0].height * width / frames[0].width))
    scaled = [f.resize((width, height), Image.Resampling.LANCZOS) for f in frames]
    out = io.BytesIO()
    options = {"quality": 70, "method": 4} if suffix == ".webp" else {"optimize": True}
    scaled[0].save(
        out,
        format=FORMATS[suffix],
        save_all=True,
        append_images=scaled[1:],
        duration=round(1000 / fps),
        loop=0,
        **options,
    )
    return out.getvalue()


def animate(
    frames: list[Image.Image], fps: float, every: int, width: int, max_bytes: int, suffix: str
) -> tuple[bytes, dict]:
    """The largest (frame rate first, then width) animation under ``max_bytes``."""
    while True:
        kept = frames[::every]
        data = encode(kept, fps / every, width, suffix)
        if len(data) <= max_bytes:
            return data, {"frames": len(kept), "fps": fps / every, "width": width, "bytes": len(data)}
        if len(kept) > 8:
            every *= 2  # a coarser frame rate first: the motion stays readable
        elif width > 64:
            width //= 2
        else:
            raise ValueError(
                f"The animation is {len(data) // 1024} KB even at {len(kept)} frames and {width} px: raise "
                "--max_kb, or trim the video."
            )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("video", type=Path, help="a lerobot-eval mp4, or the eval's --output_dir")
    parser.add_argument("--output", type=Path, required=True, help="the .webp or .gif to write")
    parser.add_argument("--every", type=int, default=2, help="keep one frame in this many (default 2)")
    parser.add_argument("--width", type=int, default=256, help="width in pixels (default 256)")
    parser.add_argument("--max_kb", type=int, default=1000, help="size limit in KB (default 1000)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")


def run(args: argparse.Namespace) -> None:
    suffix = args.output.suffix.lower()
    if suffix not in FORMATS:
        raise SystemExit(f"--output must end in {' or '.join(FORMATS)}, got {args.output.name!r}.")
    if args.every < 1 or args.width < 1:
        raise SystemExit("--every and --width must be positive.")
    if args.output.exists() and not args.overwrite:
        raise SystemExit(f"{args.output} exists: pass --overwrite to replace it.")
    video = episode_video(args.video)
    frames, fps = read_frames(video)
    data, kept = animate(frames, fps, args.every, args.width, args.max_kb * 1000, suffix)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(data)
    logging.info(
        "%s -> %s: %d of %d frames at %.1f fps, %d px wide, %d KB",
        video, args.output, kept["frames"], len(frames), kept["fps"], kept["width"], kept["bytes"] // 1000,
    )  # fmt: skip
