"""`lerobot-sdp-bench deployment` on a tiny SDP: sync, RTC and async through the real CLIs on
pusht_sim, a row per engine with the robot's records; refusals named (plumbing, not timed)."""

import json

import pytest
from sdp_test_utils import PUSHT_KEYPOINT_STATS, save_tiny_policy, tiny_config

from lerobot_sdp.benchmarks import cli, deployment


@pytest.mark.slow
def test_every_engine_drives_the_robot_and_reports(tmp_path):
    policy = save_tiny_policy(tmp_path / "sdp")
    out = tmp_path / "out"
    port = 18000 + (hash(str(tmp_path)) % 2000)
    # three episodes two at a time: a wave of two robots (for async, two clients of one server), then one
    cli.main(["deployment", "--policy", f"tiny={policy}", "--episodes", "3", "--parallel", "2",
              "--episode_length", "15", "--rtc_threshold", "2", "--port", str(port),
              "--output_dir", str(out)])  # fmt: skip
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["engine"] for r in rows] == ["sync", "rtc", "async"]
    for row in rows:
        assert "error" not in row, row
        assert row["n_episodes"] == 3 and row["seeds"] == [100_000, 100_002] and row["parallel"] == 2
        # an episode is 15 ticks of the wall clock (fewer on success), acted on or missed
        assert all(1 <= steps <= 15 for steps in row["episode_steps"]), row
        assert 0 <= row["avg_max_reward"] <= 1 and row["missed_ticks_per_episode"] >= 0
    for engine in ("sync", "rtc", "async"):
        for i in range(3):  # one episode per run, each robot seeded apart
            stats = json.loads((out / "stats" / f"tiny_{engine}_{i:03d}.json").read_text())
            assert len(stats["episodes"]) == 1 and stats["seed"] == 100_000 + i
    table = (out / "results.md").read_text()
    assert table.count("| tiny |") == 3 and (out / "logs" / "tiny_async_server.log").exists()


def test_rtc_row_for_a_policy_without_rtc_and_refused_checkpoints(tmp_path):
    import argparse

    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.processor import make_default_pre_post_processors

    cfg = tiny_config()
    dp = tmp_path / "dp"
    DiffusionConfig(input_features=cfg.input_features, output_features=cfg.output_features).save_pretrained(
        dp
    )
    args = argparse.Namespace(episodes=1, parallel=1, seed=0, output_dir=tmp_path / "out")
    row = deployment.measure("dp", dp, "rtc", args)
    assert "no RTC support" in row["error"] and "actions_sent" not in row

    old = save_tiny_policy(tmp_path / "old")  # then saved again with LeRobot's default pipeline
    for pipeline in make_default_pre_post_processors(cfg, PUSHT_KEYPOINT_STATS):
        pipeline.save_pretrained(old)
    assert "prepare_policy" in deployment.robot_ready_problem(old)
    assert deployment.robot_ready_problem(save_tiny_policy(tmp_path / "new")) is None
    with pytest.raises(SystemExit, match="NAME=PATH"):
        cli.main(["deployment", "--policy", str(old)])
    with pytest.raises(SystemExit, match="prepare_policy"):
        cli.main(["deployment", "--policy", f"old={old}", "--output_dir", str(tmp_path / "x")])
