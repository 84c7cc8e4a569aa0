"""The Push-T main job (`lerobot-sdp-pusht`) end to end on a tiny dataset, then `--resume`."""

import json
from pathlib import Path

import pytest
from sdp_test_utils import make_tiny_pusht_dataset, tiny_job_config

from lerobot_sdp.pusht import job
from lerobot_sdp.pusht.evaluation import pusht_eval_args


@pytest.mark.slow
def test_main_job_then_resume_keeps_the_first_runs_timings(tmp_path, monkeypatch, capsys):
    """The job end to end on a tiny dataset and config (2 steps, 1 short episode), then `--resume`."""
    dataset = tmp_path / "dataset"
    make_tiny_pusht_dataset(dataset)
    config_path = tmp_path / "tiny.json"
    # max_delay 1 fits the padding of h = 2
    tiny_job_config("pusht_state_cpu", config_path, {"n_chunks": 2, "max_delay": 1})
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
    steps = json.loads(config_path.read_text())["steps"]
    assert first["train_steps"] == steps
    assert first["train_steps_per_s"] == steps / first["stage_time_s"]["train"]
    assert "steps/s (start-up and checkpoints included;" in first_out

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
