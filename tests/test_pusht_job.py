"""The Push-T main job (`lerobot-sdp-pusht`): its console summary, the SDP geometry it prints before
training, and per-stage timings that survive `--resume`."""

import json
from pathlib import Path

import pytest
from sdp_test_utils import make_tiny_pusht_dataset

from lerobot_sdp.pusht import job
from lerobot_sdp.pusht.evaluation import pusht_eval_args
from lerobot_sdp.pusht.job import StageTimings, print_summary, sdp_geometry

REPO = Path(__file__).resolve().parents[1]


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(job.time, "monotonic", clock)
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
    }
    print_summary(summary, tmp_path)
    out = capsys.readouterr().out
    assert "123.4 ms per chunk" in out
    assert "checkpoint          out/train/checkpoints/last/pretrained_model" in out
    assert "videos              out/eval/videos  (1 episodes rendered as .mp4)" in out
    assert "195 s in all (data 12 s, train 150 s, eval 30 s, measure 3 s; resumed in session 2" in out
    assert "train reused, eval ran" in out


@pytest.mark.slow
def test_main_job_then_resume_keeps_the_first_runs_timings(tmp_path, monkeypatch, capsys):
    """The job end to end on a tiny dataset and config (2 steps, 1 short episode), then `--resume`."""
    dataset = tmp_path / "dataset"
    make_tiny_pusht_dataset(dataset)
    config = json.loads((REPO / "configs" / "pusht_state_cpu.json").read_text())
    config["policy"] |= {
        "down_dims": [16, 32],
        "diffusion_step_embed_dim": 16,
        "n_action_steps": 4,
        "n_chunks": 2,
        "num_train_timesteps": 10,
        "num_inference_steps": 10,
        "scheduler_warmup_steps": 0,
        "max_delay": 1,  # fits the padding
    }
    config |= {"steps": 2, "batch_size": 4, "log_freq": 1}
    config_path = tmp_path / "tiny.json"
    config_path.write_text(json.dumps(config))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("WANDB_MODE", "disabled")
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(
        job,
        "keypoints_dataset_args",
        lambda zarr, data_dir: ["--dataset.repo_id=local/tiny_pusht", f"--dataset.root={dataset}"],
    )
    monkeypatch.setattr(job, "pusht_eval_args", lambda *a: pusht_eval_args(*a, episode_length=16))
    out_dir = tmp_path / "out"
    argv = [f"--output_dir={out_dir}", f"--config_path={config_path}", "--eval_episodes=1"]

    job.main(argv)
    first_out = capsys.readouterr().out
    first = json.loads((out_dir / "summary.json").read_text())
    geometry = (
        "SDP geometry: horizon=10 (1 past + room for 1 committed + 2 chunks x 4 + 0 padding), "
        "5 denoiser calls per chunk"
    )
    assert geometry in first_out
    assert first_out.index(geometry) < first_out.index("lerobot-train")  # printed before training
    assert "ms per chunk" in first_out and "checkpoints/last/pretrained_model" in first_out
    assert first["video_files"] and Path(first["video_files"][0]).exists()
    assert f"videos              {out_dir / 'eval' / 'videos'}" in first_out
    assert first["resumed"] is False and first["latency_per_chunk_ms"] > 0

    job.main([*argv, "--resume"])
    second = json.loads((out_dir / "summary.json").read_text())
    for stage in ("train", "eval"):
        assert second["stage_time_s"][stage] == first["stage_time_s"][stage]
    assert second["resumed"] is True
    assert second["sessions"][-1]["stages"] == {
        "data": "ran again",  # the tiny dataset stands in for the conversion: nothing to reuse
        "train": "reused",
        "eval": "reused",
        "measure": "ran",
    }
    assert second["pc_success"] == first["pc_success"]
