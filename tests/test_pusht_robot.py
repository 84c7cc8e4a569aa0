"""`--robot.type=pusht_sim` (Push-T on gym-pusht as a LeRobot robot) and SDP under `lerobot-rollout`."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from sdp_test_utils import PUSHT_KEYPOINT_STATS as STATS
from sdp_test_utils import save_tiny_policy, tiny_config

BIN = Path(sys.executable).parent


def make_robot(tmp_path, **kwargs):
    from lerobot.robots.utils import make_robot_from_config

    from lerobot_sdp.robots import PushTSimConfig

    return make_robot_from_config(PushTSimConfig(calibration_dir=tmp_path / "calibration", **kwargs))


def test_import_registers_the_robot_without_gym_pusht():
    """The plugin's import registers `pusht_sim`; gym-pusht loads only when the robot connects."""
    code = (
        "import sys, lerobot_sdp; from lerobot.robots import RobotConfig; "
        "print(RobotConfig.get_choice_class('pusht_sim').__name__, 'gym_pusht' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["PushTSimConfig", "False"]


def clocked(tmp_path, monkeypatch, **kwargs):
    """A connected robot on a wall clock the test sets (`now[0]`, seconds)."""
    from lerobot_sdp.robots import pusht_sim

    now = [0.0]
    monkeypatch.setattr(pusht_sim.time, "perf_counter", lambda: now[0])
    robot = make_robot(tmp_path, **kwargs)
    robot.connect()
    return robot, now


def act(robot, x: float = 100.0, y: float = 120.0) -> dict:
    return robot.send_action({"agent_x.pos": x, "agent_y.pos": y})


def test_robot_features_one_episode_and_its_stats(tmp_path, monkeypatch):
    from lerobot_sdp.robots.pusht_sim import AGENT_KEYS, PushTSim

    robot, now = clocked(tmp_path, monkeypatch, episode_length=3, stats_path=tmp_path / "stats.json")
    assert isinstance(robot, PushTSim)
    assert list(robot.action_features) == list(AGENT_KEYS)
    features = robot.observation_features
    assert len(features) == 18 and all(v is float and k.endswith(".pos") for k, v in features.items())
    try:
        obs = robot.get_observation()
        assert list(obs) == list(features)
        assert act(robot) == {"agent_x.pos": 100.0, "agent_y.pos": 120.0}
        assert robot.get_observation()["agent_x.pos"] != obs["agent_x.pos"]  # the pusher moved
        assert 0.0 <= robot.last_reward <= 1.0
        for tick in (1, 2):
            now[0] = 0.1 * tick
            act(robot)
        # the episode ended after 3 ticks: the robot holds still, the env does not reset under the policy
        over = robot.get_observation()
        assert len(robot.episodes) == 1 and robot.episodes[0]["steps"] == 3
        now[0] = 0.3
        act(robot, 400.0, 400.0)
        now[0] = 5.0
        assert robot.get_observation() == over and robot.actions_after_end == 1
        # LeRobot's return-to-initial-position (all `.pos` keys) does not step the env
        robot.send_action(dict(obs))
        assert robot.actions_sent == 3 and robot.ignored_commands == 1
        with pytest.raises(KeyError):
            robot.send_action({"agent_x.pos": 1.0})
    finally:
        robot.disconnect()
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["actions_sent"] == 3 and len(stats["episodes"]) == 1 and stats["missed_ticks"] == 0
    assert set(stats["episodes"][0]) >= {"max_reward", "success", "steps"}


def test_the_env_advances_with_the_wall_clock_and_a_stall_holds_the_last_target(tmp_path, monkeypatch):
    """10 Hz: an action 0.34 s after the previous one finds 2 ticks passed without one; the env stepped
    them with the last target (the pusher kept moving towards it) and counts them as missed."""
    robot, now = clocked(tmp_path, monkeypatch)
    twin = make_robot(tmp_path / "twin")  # the same start, on the same clock
    twin.connect()
    try:
        for t, x in zip((0.0, 0.1, 0.2), (100.0, 103.0, 107.0), strict=True):
            now[0] = t
            act(robot, x, 200.0)
            act(twin, x, 200.0)
        for t in (0.3, 0.4):  # the twin's actions on time: the last target again
            now[0] = t
            act(twin, 107.0, 200.0)
        now[0] = 0.54
        stalled = robot.get_observation()  # read during the stall: already 2 ticks further
        assert robot.missed_ticks == 2 and len(robot.rewards) == 5
        assert stalled == twin.get_observation() and twin.missed_ticks == 0
        act(robot, 227.0, 200.0)
        now[0] = 0.64
        act(robot, 227.0, 200.0)
        stats = robot.stats()
    finally:
        robot.disconnect()
        twin.disconnect()
    assert stats["missed_ticks"] == 2 and stats["current_episode"]["steps"] == 7
    assert stats["action_jump_px"]["max"] == 120.0 and stats["action_jump_px"]["n"] == 4
    assert stats["action_jump_px"]["p50"] == 3.5  # jumps 3, 4, 120, 0
    assert stats["longest_gap_s"] == pytest.approx(0.34)  # 0.2 -> 0.54: the stall


def test_an_action_early_for_its_tick_is_the_next_ticks_target(tmp_path, monkeypatch):
    robot, now = clocked(tmp_path, monkeypatch)
    try:
        act(robot, 100.0, 100.0)
        now[0] = 0.02
        act(robot, 300.0, 300.0)  # tick 0 already stepped: nothing steps now
        assert len(robot.rewards) == 1
        now[0] = 0.13
        robot.get_observation()  # within tick 1's window: its action may still come
        assert len(robot.rewards) == 1
        now[0] = 0.16
        robot.get_observation()  # tick 1 passed without an action: it held the early target
        assert len(robot.rewards) == 2 and robot.missed_ticks == 1
    finally:
        robot.disconnect()


def test_robot_warns_when_driven_faster_than_real_time(tmp_path, caplog):
    robot = make_robot(tmp_path)
    robot.connect()
    try:
        with caplog.at_level("WARNING"):
            for _ in range(25):  # back to back, far faster than 10 Hz
                robot.send_action({"agent_x.pos": 256.0, "agent_y.pos": 256.0})
        assert len(robot.rewards) <= 2  # early actions replace the target, the env keeps real time
    finally:
        robot.disconnect()
    assert "Pass --fps=10" in caplog.text


def test_sdp_preprocessor_splits_the_robot_state():
    """LeRobot joins a robot's scalars into one `observation.state` (18,); SDP's preprocessor splits it
    into the (2,) state and (16,) environment state the policy was trained on."""
    from lerobot_sdp import SDPPolicy, make_sdp_pre_post_processors

    cfg = tiny_config()
    pre, post = make_sdp_pre_post_processors(cfg, STATS)
    joined = {"observation.state": torch.rand(1, 18) * 512, "task": "", "robot_type": "pusht_sim"}
    out = pre(dict(joined))
    assert out["observation.state"].shape == (1, 2) and out["observation.environment_state"].shape == (1, 16)
    separate = pre(
        {
            "observation.state": joined["observation.state"][:, :2],
            "observation.environment_state": joined["observation.state"][:, 2:],
        }
    )
    for key in ("observation.state", "observation.environment_state"):
        assert torch.equal(out[key], separate[key])
    action = post(SDPPolicy(cfg).select_action(out))
    assert action.shape == (1, 2)
    with pytest.raises(ValueError, match="environment-state"):
        pre({"observation.state": torch.rand(1, 5)})


def test_add_split_state_step_upgrades_an_older_checkpoint(tmp_path):
    """A checkpoint saved with LeRobot's default pipeline (before `sdp_split_state`) gets the step."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor import make_default_pre_post_processors

    from lerobot_sdp import SDPPolicy
    from lerobot_sdp.processor_sdp import PREPROCESSOR_FILE, add_split_state_step

    cfg = tiny_config()
    SDPPolicy(cfg).save_pretrained(tmp_path)
    for pipeline in make_default_pre_post_processors(cfg, STATS):
        pipeline.save_pretrained(tmp_path)
    cli = [sys.executable, "-m", "lerobot_sdp.robots.prepare_policy", str(tmp_path)]
    out = subprocess.run(cli, capture_output=True, text=True, check=True).stdout
    assert "added sdp_split_state" in out and not add_split_state_step(tmp_path)
    steps = json.loads((tmp_path / PREPROCESSOR_FILE).read_text())["steps"]
    assert [s["registry_name"] for s in steps][:2] == ["rename_observations_processor", "sdp_split_state"]
    state_files = {s["state_file"] for s in steps if "state_file" in s}
    assert {p.name for p in tmp_path.glob("policy_preprocessor_step_*")} == state_files
    pre, _ = make_pre_post_processors(cfg, pretrained_path=str(tmp_path))
    out = pre({"observation.state": torch.rand(1, 18) * 512})
    assert out["observation.environment_state"].shape == (1, 16)


def run_rollout(tmp_path, duration: int, *extra: str) -> tuple[str, dict]:
    """The real `lerobot-rollout` CLI on pusht_sim at 10 Hz with a tiny SDP: its log and robot stats."""
    policy_dir = save_tiny_policy(tmp_path / "policy")
    stats_path = tmp_path / "rollout_stats.json"
    cmd = [
        str(BIN / "lerobot-rollout"),
        "--robot.type=pusht_sim",
        f"--robot.calibration_dir={tmp_path / 'calibration'}",
        f"--robot.stats_path={stats_path}",
        f"--policy.path={policy_dir}",
        "--fps=10",
        f"--duration={duration}",
        "--device=cpu",
        "--return_to_initial_position=false",
        *extra,
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_LEROBOT_HOME": str(tmp_path / "lerobot_home")}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-5000:]
    return log, json.loads(stats_path.read_text())


@pytest.mark.slow
def test_lerobot_rollout_drives_pusht_sim_with_sdp(tmp_path):
    """The real `lerobot-rollout` CLI (sync engine) runs SDP on the simulated robot at 10 Hz."""
    duration = 3
    log, stats = run_rollout(tmp_path, duration)
    assert "SyncInferenceEngine" in log and "Rollout finished" in log
    # paced at 10 Hz for `duration` s: about 30 actions (fewer on a slow or loaded machine)
    assert 10 <= stats["actions_sent"] <= 10 * duration + 2, stats
    assert stats["ignored_commands"] == 0
    episode = stats["current_episode"]
    # every tick of the wall clock ran: with an action, or held (a missed tick, e.g. on a busy machine)
    acted = stats["actions_sent"] - stats["early_actions"]
    assert episode["steps"] == acted + stats["missed_ticks"] and 0.0 <= episode["max_reward"] <= 1.0
    assert "pusht_sim disconnected after" in log


@pytest.mark.slow
def test_lerobot_rollout_rtc_engine_drives_pusht_sim_with_sdp(tmp_path):
    """The real `lerobot-rollout` CLI with the RTC engine (a background inference thread) runs SDP,
    called once per chunk (`--inference.queue_threshold` below the chunk length)."""
    duration = 5
    log, stats = run_rollout(tmp_path, duration, "--inference.type=rtc", "--inference.queue_threshold=2")
    assert "RTCInferenceEngine" in log and "RTC inference error" not in log, log[-5000:]
    assert 2 * duration <= stats["actions_sent"] <= 10 * duration + 2, stats
    assert stats["ignored_commands"] == 0


def test_a_reconnect_starts_a_new_episode(tmp_path, monkeypatch):
    """After disconnect() / connect() the robot runs a new episode: its actions step the env again
    (not "after the end"), on a clock that starts with its first action; finished episodes are kept."""
    robot, now = clocked(tmp_path, monkeypatch, episode_length=3)
    for tick in range(4):
        now[0] = tick * 0.1
        act(robot)
    assert robot.stats()["actions_after_end"] == 1 and len(robot.episodes) == 1
    robot.disconnect()
    now[0] = 50.0  # long after the first connection's clock started: no tick may count as missed
    robot.connect()
    try:
        act(robot)
        stats = robot.stats()
        assert stats["actions_after_end"] == 0 and stats["missed_ticks"] == 0 and stats["actions_sent"] == 1
        assert stats["current_episode"]["steps"] == 1 and len(stats["episodes"]) == 1
    finally:
        robot.disconnect()
