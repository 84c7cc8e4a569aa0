"""The scripted Lift demonstrator: episodes end at success, or `hold_steps` later still lifting."""

import numpy as np
import pytest

pytest.importorskip(
    "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
)

from lerobot_sdp.robomimic.env import RobomimicEnv
from lerobot_sdp.robomimic.scripted_lift import LiftDemonstrator, _run_episode, record


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


def test_negative_hold_steps_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="--hold_steps must be 0 or more"):
        record(1, tmp_path / "demos", hold_steps=-1)
