"""The staged main job shared by the Push-T and robomimic commands: its console summary, the SDP
geometry it prints before training, and per-stage timings that survive `--resume`."""

import json
from pathlib import Path

import pytest

from lerobot_sdp import main_job
from lerobot_sdp.main_job import StageTimings, print_summary, sdp_geometry

REPO = Path(__file__).resolve().parents[1]


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(main_job.time, "monotonic", clock)
    return clock


def run_stage(timings: StageTimings, clock: Clock, name: str, seconds: float, **kwargs) -> None:
    with timings.stage(name, **kwargs):
        clock.now += seconds


def test_resumed_session_keeps_reused_stage_times_and_adds_resumed_ones(tmp_path, clock):
    first = StageTimings(tmp_path)
    run_stage(first, clock, "data", 12.0)
    with pytest.raises(KeyboardInterrupt), first.stage("train"):  # Ctrl-C during training
        clock.now += 100.0
        raise KeyboardInterrupt
    assert json.loads((tmp_path / "timings.json").read_text())["stage_s"] == {"data": 12.0, "train": 100.0}
    assert not first.resumed

    second = StageTimings(tmp_path)  # --resume: data reused, training resumed from its checkpoint
    run_stage(second, clock, "data", 0.1, reused=True)
    run_stage(second, clock, "train", 50.0)
    run_stage(second, clock, "eval", 30.0)
    run_stage(second, clock, "measure", 2.0, replace=True)

    third = StageTimings(tmp_path)  # --resume on a finished run: everything reused but the measurement
    for name in ("data", "train", "eval"):
        run_stage(third, clock, name, 0.1, reused=True)
    run_stage(third, clock, "measure", 3.0, replace=True)
    summary = third.summary()

    assert summary["stage_time_s"] == {"data": 12.0, "train": 150.0, "eval": 30.0, "measure": 3.0}
    assert summary["wall_time_s"] == 195.0
    assert summary["train_and_data_time_s"] == 162.0
    assert summary["resumed"] is True
    assert [s["stages"] for s in summary["sessions"]] == [
        {"data": "ran", "train": "interrupted"},
        {"data": "reused", "train": "resumed", "eval": "ran", "measure": "ran"},
        {"data": "reused", "train": "reused", "eval": "reused", "measure": "ran"},
    ]

    fourth = StageTimings(tmp_path)  # a finished stage done again (e.g. eval_info.json deleted): time adds up
    run_stage(fourth, clock, "eval", 20.0)
    assert fourth.summary()["stage_time_s"]["eval"] == 50.0
    assert fourth.session["stages"] == {"eval": "ran again"}


def test_sdp_geometry_of_the_main_jobs_config():
    config = json.loads((REPO / "configs" / "pusht_state_cpu.json").read_text())
    line = sdp_geometry(config, "cpu")
    assert line.startswith("SDP geometry: horizon=36 (1 past + 4 chunks x 8 + 3 padding)")
    assert "4 denoiser calls per chunk (N = 16, h = 4)" in line
    assert sdp_geometry({"policy": {"type": "diffusion"}}, "cpu") is None


def test_console_summary_shows_latency_checkpoint_videos_and_resume(tmp_path, capsys):
    summary = {
        "pc_success": 2.0,
        "avg_max_reward": 0.446,
        "n_episodes": 50,
        "denoiser_calls_per_chunk": 50.0,
        "latency_per_chunk_ms": 123.4,
        "latency_device": "cpu",
        "num_inference_steps": 100,
        "n_chunks": 2,
        "model_dir": "out/train/checkpoints/last/pretrained_model",
        "videos": "out/eval/videos",
        "video_files": ["out/eval/videos/pusht_0/eval_episode_0.mp4"],
        "wall_time_s": 195.0,
        "stage_time_s": {"data": 12.0, "train": 150.0, "eval": 30.0, "measure": 3.0},
        "resumed": True,
        "sessions": [{"stages": {"train": "ran"}}, {"stages": {"train": "reused", "eval": "ran"}}],
        "train_steps": 300,
        "train_steps_per_s": 2.0,
        "train_torch_threads": 2,
        "train_num_workers": 0,
        "train_precision": "bf16 autocast",
    }
    print_summary("SDP on Push-T (keypoints)", summary, tmp_path)
    out = capsys.readouterr().out
    assert "=== SDP on Push-T (keypoints) ===" in out
    assert "123.4 ms per chunk" in out
    assert "checkpoint          out/train/checkpoints/last/pretrained_model" in out
    assert "videos              out/eval/videos  (1 episodes rendered as .mp4)" in out
    assert "195 s in all (data 12 s, train 150 s, eval 30 s, measure 3 s; resumed in session 2" in out
    assert "train reused, eval ran" in out
    assert "300 steps, 2.00 steps/s (start-up and checkpoints included; 2 torch threads, 0 DataLoader" in out
    assert "0 DataLoader workers, bf16 autocast)" in out


def test_the_pusht_job_picks_its_precision_by_the_cpu_and_the_robomimic_job_trains_fp32():
    from lerobot_sdp.pusht.job import parse_args as pusht_args
    from lerobot_sdp.robomimic.job import parse_args as robomimic_args

    assert pusht_args([]).precision == "auto"  # bf16 measured equal on Push-T
    assert robomimic_args([]).precision == "fp32"  # and not yet on Can
    assert robomimic_args(["--precision", "auto"]).precision == "auto"
