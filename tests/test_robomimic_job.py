"""The robomimic main job (`lerobot-sdp-robomimic`): scripted demonstrations -> lerobot-train ->
lerobot-eval -> summary, end to end on a tiny budget, then `--resume` reusing every stage."""

import json
from pathlib import Path

import pytest
from sdp_test_utils import tiny_job_config

pytest.importorskip(
    "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
)

from lerobot_sdp import shipped_configs
from lerobot_sdp.robomimic import job
from lerobot_sdp.robomimic.evaluation import robomimic_eval_args


def test_each_task_trains_from_its_shipped_config():
    assert job.parse_args([]).config_path == shipped_configs.path("robomimic_can_lowdim_cpu")
    assert job.parse_args(["--task", "Lift"]).config_path == shipped_configs.path("robomimic_lift_lowdim_cpu")
    for task, name in job.CONFIGS.items():
        config = json.loads(shipped_configs.path(name).read_text())
        assert config["env"]["task"] == task and config["policy"]["type"] == "sdp"
    with pytest.raises(SystemExit):
        job.parse_args(["--num_demos", "0"])


def test_a_moved_recording_is_reused_from_where_it_is_now(tmp_path):
    """A recording.json written before the root was derived names the folder it was recorded into;
    reused from a copied output folder, training must read the copy, not the original (which may be
    gone)."""
    old, new = tmp_path / "old" / "data", tmp_path / "new" / "data"
    new.mkdir(parents=True)
    stats = {"successes": 2, "repo_id": "local/scripted_lift", "root": str(old / "demos")}
    (new / job.RECORDING).write_text(json.dumps(stats))
    reused = job.record_demonstrations("Lift", 2, new)
    assert reused["root"] == str(new / "demos") and reused["successes"] == 2
    assert f"--dataset.root={new / 'demos'}" in job.dataset_args(reused)


@pytest.mark.slow
def test_main_job_records_trains_evaluates_and_resumes(tmp_path, monkeypatch, capsys):
    config_path = tmp_path / "tiny.json"
    tiny_job_config("robomimic_can_lowdim_cpu", config_path, num_workers=0)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("WANDB_MODE", "disabled")
    monkeypatch.setattr(job, "robomimic_eval_args", lambda *a: robomimic_eval_args(*a, episode_length=12))
    out_dir = tmp_path / "out"
    argv = [f"--output_dir={out_dir}", f"--config_path={config_path}", "--num_demos=2", "--eval_episodes=1"]

    job.main(argv)
    out = capsys.readouterr().out
    assert "Scripted PickPlaceCan: 2/2 attempts succeeded (100.0%)" in out
    assert "=== SDP on robomimic PickPlaceCan (low-dim, scripted demonstrations) ===" in out
    first = json.loads((out_dir / "summary.json").read_text())
    assert first["task"] == "PickPlaceCan" and first["n_episodes"] == 1
    assert first["demonstrations"]["successes"] == 2 and first["demonstrations"]["success_rate"] == 1.0
    assert first["denoiser_calls_per_chunk"] == 5  # N = 10 over h = 2 chunks
    assert first["video_files"] and Path(first["video_files"][0]).exists()

    job.main([*argv, "--resume"])
    second = json.loads((out_dir / "summary.json").read_text())
    assert second["sessions"][-1]["stages"] == {
        "data": "reused",
        "train": "reused",
        "eval": "reused",
        "measure": "ran",
    }
    assert second["demonstrations"] == first["demonstrations"]
    assert second["stage_time_s"]["data"] == first["stage_time_s"]["data"]
