"""Recording scripted demonstrations: only successes are kept, episodes end at success (or
`hold_steps` later, the demonstrator still acting), bad arguments are clear errors."""

import json

import numpy as np
import pytest

pytest.importorskip(
    "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
)

from lerobot_sdp.robomimic.demonstrators import LiftDemonstrator
from lerobot_sdp.robomimic.env import RobomimicEnv
from lerobot_sdp.robomimic.record_scripted import _run_episode, main, record


@pytest.fixture(scope="module")
def lift_env():
    env = RobomimicEnv("Lift")
    yield env
    env.close()


def episode(env: RobomimicEnv, hold_steps: int) -> list[dict]:
    # The same seeds give the same scene and the same demonstrator style.
    return _run_episode(env, LiftDemonstrator(np.random.default_rng(0)), 100_000, "lift", hold_steps)


def test_hold_steps_extend_the_episode_past_success(lift_env):
    short, held = episode(lift_env, 0), episode(lift_env, 10)
    assert len(held) == len(short) + 10
    done = [bool(f["next.done"][0]) for f in held]
    assert done == [False] * (len(held) - 1) + [True]  # done only on the last frame
    rewards = np.array([f["next.reward"][0] for f in held])
    assert rewards[len(short) - 1 :].min() == 1.0  # the cube stays up while the demonstrator holds it
    assert held[-1]["observation.environment_state"][2] > short[-1]["observation.environment_state"][2]


def test_can_demonstrations_are_recorded_with_the_success_rate(tmp_path, capsys):
    data = tmp_path / "can"
    main(["--task", "PickPlaceCan", "--num_episodes", "2", "--output_dir", str(data)])
    out = capsys.readouterr().out
    assert "Scripted PickPlaceCan: 2/2 attempts succeeded (100.0%)" in out
    info = json.loads((data / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2
    assert info["features"]["observation.environment_state"]["shape"] == [14]
    assert info["features"]["action"]["shape"] == [7]
    # Every episode ends at the frame the task counted as a success: reward 1 there and only there.
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    frames = LeRobotDataset("local/scripted_pickplacecan", root=data).hf_dataset.with_format("numpy")
    for ep in (0, 1):
        ep_frames = frames.filter(lambda f, ep=ep: f["episode_index"] == ep)
        rewards = np.asarray(ep_frames["next.reward"]).ravel()
        assert rewards[-1] == 1.0 and rewards[:-1].max() == 0.0
        assert np.asarray(ep_frames["next.done"]).ravel().tolist() == [False] * (len(rewards) - 1) + [True]


def test_bad_arguments_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="--hold_steps must be 0 or more"):
        record(1, tmp_path / "demos", hold_steps=-1)
    with pytest.raises(ValueError, match="No scripted demonstrator for 'ToolHang'"):
        record(1, tmp_path / "demos", task="ToolHang")
    with pytest.raises(SystemExit):
        main(["--task", "ToolHang", "--num_episodes", "1", "--output_dir", str(tmp_path / "demos")])
