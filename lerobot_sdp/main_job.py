"""The staged main job shared by `lerobot-sdp-pusht` and `lerobot-sdp-robomimic`.

Stages: data (the task's), train (`lerobot-train --config_path=...`), eval (`lerobot-eval`), measure
(denoiser calls and latency per chunk of the trained checkpoint). The job prints pc_success, the
denoiser calls and latency per chunk, the checkpoint and where lerobot-eval wrote the rollout videos;
OUTPUT_DIR/summary.json has all of it.

Stages that already finished are reused with --resume (an interrupted training run resumes from
its last checkpoint); an existing output directory is never overwritten without --overwrite.
Each stage's wall time is kept in OUTPUT_DIR/timings.json as soon as it finishes (or stops), so a
resumed run reports the time its reused stages took in the session that ran them.
"""

import argparse
import json
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path

import draccus
from lerobot.configs.policies import PreTrainedConfig

from . import shipped_configs
from .chunk_cost import stream_cost
from .lerobot_cli import (
    PRECISIONS,
    CLIError,
    eval_info,
    evaluate,
    num_workers,
    train,
    trained_precision,
    trained_steps,
    training_threads,
)

STAGES = ("data", "train", "eval", "measure")


def job_parser(
    description: str, output_dir: str, config: str | None, precision: str = "auto"
) -> argparse.ArgumentParser:
    """The options every main job has; the task adds its data options. `config`: the shipped config
    by default (None: the task picks one after parsing); `precision`: the default of --precision."""
    p = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output_dir", type=Path, default=Path(output_dir))
    p.add_argument(
        "--config_path",
        type=shipped_configs.config_argument,
        default=config,
        help="a config file, or the name of a shipped one (python -m lerobot_sdp.shipped_configs)",
    )
    p.add_argument("--eval_episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=None, help="override the config's training steps")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--precision",
        choices=PRECISIONS,
        default=precision,
        help=f"training precision (default: {precision}); auto: bf16 autocast on a CPU with native bf16 "
        "(avx512_bf16, AMX), else fp32",
    )
    group = p.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true", help="reuse finished stages, resume training")
    group.add_argument("--overwrite", action="store_true", help="delete --output_dir and start over")
    return p


def prepare_output_dir(args: argparse.Namespace) -> None:
    if args.output_dir.exists() and any(args.output_dir.iterdir()):
        if args.overwrite:
            shutil.rmtree(args.output_dir)
        elif not args.resume:
            sys.exit(
                f"error: {args.output_dir} already exists. Pass --resume to reuse finished stages "
                "(and resume training), --overwrite to delete it, or another --output_dir."
            )
    args.output_dir.mkdir(parents=True, exist_ok=True)


class StageTimings:
    """Wall time of each stage of one output directory, kept in OUTPUT_DIR/timings.json across sessions.

    A stage's seconds are the time spent doing its work, summed over the sessions that did some: a
    session that finds the stage finished (reused) adds nothing, one that resumes it (training from its
    last checkpoint) adds its own time, and a stage that stops (error, Ctrl-C) records the time it had
    spent. `measure` (the latency per chunk) is measured again in every session: its time is replaced.
    Each session lists what it did per stage: ran, reused, resumed (after an interruption), ran again
    (after a finished run, e.g. more --steps), interrupted.
    """

    FILE = "timings.json"

    def __init__(self, output_dir: Path):
        self.path = output_dir / self.FILE
        saved = json.loads(self.path.read_text()) if self.path.exists() else {}
        self.stage_s: dict[str, float] = saved.get("stage_s", {})
        self.sessions: list[dict] = saved.get("sessions", [])
        self.session: dict = {"started": datetime.now().isoformat(timespec="seconds"), "stages": {}}
        self.sessions.append(self.session)
        self._start = time.monotonic()

    @property
    def resumed(self) -> bool:
        """Whether this run spans more than one session (it was resumed)."""
        return len(self.sessions) > 1

    @contextmanager
    def stage(self, name: str, reused: bool = False, replace: bool = False) -> Iterator[None]:
        if reused:
            try:
                yield
            finally:
                self.session["stages"][name] = "reused"
                self.save()
            return
        before = 0.0 if replace else self.stage_s.get(name, 0.0)
        earlier = [s["stages"][name] for s in self.sessions[:-1] if name in s["stages"]]
        if replace or not earlier:
            status = "ran"
        else:
            status = "resumed" if earlier[-1] == "interrupted" else "ran again"
        start = time.monotonic()
        try:
            yield
        except BaseException:
            status = "interrupted"
            raise
        finally:
            self.stage_s[name] = round(before + time.monotonic() - start, 1)
            self.session["stages"][name] = status
            self.save()

    def save(self) -> None:
        self.session["wall_time_s"] = round(time.monotonic() - self._start, 1)
        self.path.write_text(json.dumps({"stage_s": self.stage_s, "sessions": self.sessions}, indent=2))

    def summary(self) -> dict:
        stages = {name: self.stage_s[name] for name in STAGES if name in self.stage_s}
        return {
            "wall_time_s": round(sum(stages.values()), 1),
            "train_and_data_time_s": round(stages.get("data", 0.0) + stages.get("train", 0.0), 1),
            "stage_time_s": stages,
            "session_wall_time_s": round(time.monotonic() - self._start, 1),
            "resumed": self.resumed,
            "sessions": self.sessions,
        }


def sdp_geometry(config: dict, device: str) -> str | None:
    """The SDP geometry line of a `lerobot-train` JSON config (None for another policy type); the
    config is built exactly as lerobot-train builds it, so an invalid one fails here, before training."""
    policy = config.get("policy", {})
    if policy.get("type") != "sdp":
        return None
    g = draccus.decode(PreTrainedConfig, {**policy, "device": device}).geometry
    return f"{g.describe()} (N = {g.num_inference_steps}, h = {g.n_chunks})."


def rollout_videos(eval_dir: Path) -> list[Path]:
    """The episode videos lerobot-eval rendered (its first 10 episodes)."""
    return sorted((eval_dir / "videos").rglob("*.mp4"))


def train_evaluate_measure(
    args: argparse.Namespace,
    timings: StageTimings,
    dataset_args: list[str],
    eval_args: list[str],
    job_name: str,
) -> dict:
    """The train, eval and measure stages on the data the task's stage prepared (`dataset_args`, flags
    of lerobot-train); `eval_args` are lerobot-eval's flags, --policy.device included. The summary dict."""
    config = json.loads(args.config_path.read_text())
    steps = args.steps or config["steps"]
    train_dir, eval_dir = args.output_dir / "train", args.output_dir / "eval"
    logs = args.output_dir / "logs"
    train_args = [
        f"--config_path={args.config_path}",
        *dataset_args,
        f"--save_freq={min(steps, 1000)}",
        f"--policy.device={args.device}",
        f"--job_name={job_name}",
    ]
    with timings.stage("train", reused=trained_steps(train_dir) >= steps):
        model_dir = train(train_dir, train_args, steps, logs / "train.log", precision=args.precision)
    with timings.stage("eval", reused=eval_info(eval_dir).exists()):
        metrics = evaluate(model_dir, eval_dir, eval_args, logs / "eval.log")
    videos = rollout_videos(eval_dir)
    print(f"[eval] {len(videos)} rollout videos in {eval_dir / 'videos'}", flush=True)
    with timings.stage("measure", replace=True):
        cost = stream_cost(model_dir)
    policy = json.loads((model_dir / "config.json").read_text())
    timing = timings.summary()
    train_s, steps_done = timing["stage_time_s"].get("train"), trained_steps(train_dir)
    return {
        "pc_success": metrics["pc_success"],
        "avg_max_reward": metrics["avg_max_reward"],
        "avg_sum_reward": metrics["avg_sum_reward"],
        "n_episodes": metrics["n_episodes"],
        **cost,
        "latency_device": "cpu",
        "num_inference_steps": policy["num_inference_steps"] or policy["num_train_timesteps"],
        "n_chunks": policy["n_chunks"],
        "model_dir": str(model_dir),
        "videos": str(eval_dir / "videos"),
        "video_files": [str(v) for v in videos],
        "train_steps": steps_done,
        "train_steps_per_s": steps_done / train_s if train_s else None,
        "train_num_workers": num_workers(train_args),
        "train_torch_threads": training_threads(train_args),
        "train_precision": trained_precision(model_dir),
        **timing,
    }


def print_summary(title: str, summary: dict, output_dir: Path) -> None:
    print(f"\n=== {title} ===")
    print(f"pc_success          {summary['pc_success']:.1f} %  over {summary['n_episodes']} episodes")
    print(f"avg_max_reward      {summary['avg_max_reward']:.3f}")
    print(
        f"denoiser calls      {summary['denoiser_calls_per_chunk']:g} per chunk (counted; N = "
        f"{summary['num_inference_steps']}, h = {summary['n_chunks']}; Diffusion Policy: N)"
    )
    print(
        f"latency             {summary['latency_per_chunk_ms']:.1f} ms per chunk "
        f"(batch 1, {summary.get('latency_device', 'cpu')}, after the first chunk)"
    )
    if summary.get("train_steps_per_s"):
        print(
            f"training            {summary['train_steps']} steps, "
            f"{summary['train_steps_per_s']:.2f} steps/s "
            f"(start-up and checkpoints included; {summary['train_torch_threads']} torch threads, "
            f"{summary['train_num_workers']} DataLoader workers, {summary.get('train_precision', 'fp32')})"
        )
    print(f"checkpoint          {summary['model_dir']}")
    n_videos = len(summary.get("video_files", []))
    print(f"videos              {summary['videos']}  ({n_videos} episodes rendered as .mp4)")
    stages = ", ".join(f"{name} {s:.0f} s" for name, s in summary["stage_time_s"].items())
    resumed = ""
    if summary["resumed"]:
        this = summary["sessions"][-1]["stages"]
        resumed = f"; resumed in session {len(summary['sessions'])}: " + ", ".join(
            f"{name} {status}" for name, status in this.items()
        )
    print(f"time                {summary['wall_time_s']:.0f} s in all ({stages}{resumed})")
    print(f"summary             {output_dir / 'summary.json'}")


def run_main(
    args: argparse.Namespace,
    run_job: Callable[[argparse.Namespace, StageTimings], dict],
    title: str,
    data_errors: tuple[type[Exception], ...] = (),
) -> None:
    """Check the config, prepare the output directory, run the job, write and print its summary;
    expected failures exit with their message, not a traceback."""
    if not args.config_path.exists():
        sys.exit(f"error: config {args.config_path} not found; pass --config_path (see the repo's configs/).")
    prepare_output_dir(args)
    try:
        config = json.loads(args.config_path.read_text())
        geometry = sdp_geometry(config, args.device)
        if geometry:
            print(f"[config] {args.config_path}: {geometry}", flush=True)
        summary = run_job(args, StageTimings(args.output_dir))
    except (CLIError, *data_errors) as e:
        sys.exit(f"error: {e}")
    except draccus.utils.DraccusException as e:
        sys.exit(f"error: {args.config_path}: invalid policy config: {e}")
    (args.output_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(title, summary, args.output_dir)
