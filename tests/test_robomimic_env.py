"""`--env.type=robomimic`: the five robomimic tasks built in robosuite, stepped with random actions."""

import subprocess
import sys

import numpy as np
import pytest

from lerobot_sdp.robomimic.config import RobomimicEnvConfig

robosuite_missing = "robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"

# task -> (state dim, object dim, action dim, episode length): robomimic's values.
EXPECTED = {
    "Lift": (9, 10, 7, 400),
    "PickPlaceCan": (9, 14, 7, 400),
    "NutAssemblySquare": (9, 14, 7, 400),
    "TwoArmTransport": (18, 41, 14, 700),
    "ToolHang": (9, 44, 7, 700),
}


def test_config_module_imports_without_robosuite():
    """LeRobot imports the config on every CLI start: it must not pull in robosuite (or need it)."""
    code = (
        "import sys, lerobot_sdp.robomimic.config; "
        "assert 'robosuite' not in sys.modules, 'robosuite imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("task", EXPECTED)
def test_config_features(task):
    from lerobot.envs.utils import env_to_policy_features

    state, obj, action, length = EXPECTED[task]
    cfg = RobomimicEnvConfig(task=task)
    assert cfg.episode_length == length
    features = {key: tuple(ft.shape) for key, ft in env_to_policy_features(cfg).items()}
    assert features == {
        "observation.state": (state,),
        "observation.environment_state": (obj,),
        "action": (action,),
    }


def test_image_config_features():
    from lerobot.envs.utils import env_to_policy_features

    cfg = RobomimicEnvConfig(task="ToolHang", obs_type="image")
    features = {key: tuple(ft.shape) for key, ft in env_to_policy_features(cfg).items()}
    assert features["observation.images.sideview"] == (3, 240, 240)
    assert features["observation.images.robot0_eye_in_hand"] == (3, 240, 240)
    assert "observation.environment_state" not in features


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"task": "Stack"}, "Unknown robomimic task"),
        ({"obs_type": "rgb"}, "obs_type"),
        ({"fps": 10}, "20 Hz"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RobomimicEnvConfig(**kwargs)


def test_registered_for_lerobot_clis():
    from lerobot.envs.factory import make_env_config

    assert isinstance(make_env_config("robomimic", task="PickPlaceCan"), RobomimicEnvConfig)


@pytest.mark.parametrize("task", EXPECTED)
def test_random_actions(task):
    """Two sub-envs per task (batched evaluation), random actions, LeRobot-shaped observations."""
    pytest.importorskip("robosuite", reason=robosuite_missing)
    from lerobot.envs.factory import make_env
    from lerobot.envs.utils import env_to_policy_features, preprocess_observation

    _, _, action, length = EXPECTED[task]
    cfg = RobomimicEnvConfig(task=task)
    envs = make_env(cfg, n_envs=2, use_async_envs=False)
    vec = envs[task][0]
    try:
        assert vec.call("_max_episode_steps") == (length, length)
        assert vec.single_action_space.shape == (action,)
        obs, _ = vec.reset(seed=[0, 1])
        for _ in range(3):
            obs, reward, terminated, truncated, info = vec.step(vec.action_space.sample())
        batch = preprocess_observation(obs)
        want = {key: (2, *ft.shape) for key, ft in env_to_policy_features(cfg).items() if key != "action"}
        assert {key: tuple(value.shape) for key, value in batch.items()} == want
        assert reward.shape == terminated.shape == truncated.shape == (2,)
        assert info["is_success"].dtype == bool
        assert not truncated.any()
    finally:
        vec.close()


@pytest.fixture(scope="module")
def lift_env():
    pytest.importorskip("robosuite", reason=robosuite_missing)
    from lerobot_sdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv("Lift", episode_length=5)
    yield env
    env.close()


def test_seeding_is_reproducible(lift_env):
    first, _ = lift_env.reset(seed=7)
    again, _ = lift_env.reset(seed=7)
    other, _ = lift_env.reset(seed=8)
    np.testing.assert_array_equal(first["environment_state"], again["environment_state"])
    assert not np.array_equal(first["environment_state"], other["environment_state"])


def test_every_env_builds_the_same_scene_for_a_seed(lift_env):
    """robosuite draws the cube's size when it builds the model: another env, built after other NumPy
    draws, must still give the same scene for the same episode seed (recording and evaluation run in
    different processes)."""
    from lerobot_sdp.robomimic.env import RobomimicEnv

    np.random.seed(12345)
    other = RobomimicEnv("Lift", episode_length=5)
    try:
        first, _ = lift_env.reset(seed=7)
        again, _ = other.reset(seed=7)
    finally:
        other.close()
    np.testing.assert_array_equal(first["environment_state"], again["environment_state"])
    np.testing.assert_array_equal(first["agent_pos"], again["agent_pos"])


def test_truncates_at_episode_length(lift_env):
    lift_env.reset(seed=0)
    flags = [lift_env.step(np.zeros(7))[3] for _ in range(5)]
    assert flags == [False] * 4 + [True]


def test_bad_action_shape(lift_env):
    lift_env.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions of shape \(7,\)"):
        lift_env.step(np.zeros(14))


def test_success_from_the_task_check():
    """The scripted demonstrator lifts the cube: the episode terminates with is_success."""
    pytest.importorskip("robosuite", reason=robosuite_missing)
    from lerobot_sdp.robomimic.demonstrators import LiftDemonstrator
    from lerobot_sdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv("Lift")
    demonstrator = LiftDemonstrator(np.random.default_rng(0))
    env.reset(seed=100_000)
    demonstrator.reset(env.sim_env)
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(demonstrator.act(env.raw_observation))
        if terminated or truncated:
            break
    env.close()
    assert terminated and info["is_success"] and reward == 1.0


def test_render_falls_back_to_black_without_gl(monkeypatch, caplog):
    pytest.importorskip("robosuite", reason=robosuite_missing)
    import lerobot_sdp.robomimic.env as env_module

    def no_gl(*args, **kwargs):
        raise RuntimeError("no GL here")

    monkeypatch.setattr(env_module, "MjRenderContextOffscreen", no_gl)
    env = env_module.RobomimicEnv("Lift", render_size=32)
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.shape == (32, 32, 3) and not frame.any()
    assert "Offscreen rendering is unavailable" in caplog.text


def _can_render() -> bool:
    """Whether robosuite gets an offscreen GL context here (the env renders black frames if not)."""
    from lerobot_sdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv("Lift", render_size=16)
    env.reset(seed=0)
    rendered = env.render().any()
    env.close()
    return bool(rendered)


def test_image_observations_and_video_frames():
    pytest.importorskip("robosuite", reason=robosuite_missing)
    if not _can_render():
        pytest.skip("no offscreen OpenGL here (set MUJOCO_GL=egl or osmesa): image observations untested")
    from lerobot.envs.utils import preprocess_observation

    envs = RobomimicEnvConfig(task="Lift", obs_type="image", render_size=64).create_envs(n_envs=1)
    vec = envs["Lift"][0]
    try:
        obs, _ = vec.reset(seed=0)
        obs, *_ = vec.step(vec.action_space.sample())
        assert (
            obs["pixels"]["agentview"].shape == (1, 84, 84, 3)
            and obs["pixels"]["agentview"].dtype == np.uint8
        )
        assert obs["pixels"]["agentview"].std() > 0  # a rendered scene, not a blank buffer
        batch = preprocess_observation(obs)
        assert tuple(batch["observation.images.robot0_eye_in_hand"].shape) == (1, 3, 84, 84)
        frame = vec.envs[0].render()
        assert frame.shape == (64, 64, 3) and frame.std() > 0
    finally:
        vec.close()


def test_another_plugins_robomimic_env_does_not_hide_sdp():
    """A second plugin that registered `--env.type=robomimic` first: SDP still imports, says which
    plugin holds the name, and `--policy.type=sdp` and `pusht_sim` stay registered."""
    code = (
        "import logging, dataclasses; logging.basicConfig(level=logging.WARNING)\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "@EnvConfig.register_subclass('robomimic')\n"
        "@dataclasses.dataclass\n"
        "class OtherRobomimic(EnvConfig):\n"
        "    pass\n"
        "import lerobot_sdp\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "from lerobot.robots import RobotConfig\n"
        "print(PreTrainedConfig.get_choice_class('sdp').__name__,"
        " RobotConfig.get_choice_class('pusht_sim').__name__,"
        " EnvConfig.get_choice_class('robomimic').__name__)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["SDPConfig", "PushTSimConfig", "OtherRobomimic"]
    assert "--env.type=robomimic is already registered by __main__.OtherRobomimic" in proc.stderr
