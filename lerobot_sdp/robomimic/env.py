"""A robomimic task (robosuite) as a gymnasium env with LeRobot's observation keys, and its vector env.

Observations: "agent_pos" (robomimic's proprioception: eef position, eef quaternion, gripper joints,
per arm), then "environment_state" (robosuite's object state, robomimic's "object") for low-dim or
"pixels" (one upright uint8 image per camera) for image observations. LeRobot's
`preprocess_observation` maps them to observation.state / .environment_state / .images.<camera>.
An episode terminates on the task's own `_check_success()` and is truncated at `episode_length`.
"""

import logging
from functools import partial
from typing import ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from lerobot.envs.utils import freeze_after_episode_end
from lerobot.utils.random_utils import seeded_context

from .tasks import CONTROL_FREQ, check_obs_type, get_task

try:
    import robosuite
    from robosuite.controllers import load_composite_controller_config
    from robosuite.utils.binding_utils import MjRenderContextOffscreen
except ModuleNotFoundError as err:
    raise ModuleNotFoundError(
        f"The robomimic environments need robosuite ({err}): pip install 'lerobot_policy_sdp[robomimic]'."
    ) from err

logger = logging.getLogger(__name__)

# robosuite draws parts of the MuJoCo model (Lift's cube size) from NumPy's global generator while it
# builds the model, once per env since soft resets keep it. Building it under one fixed seed gives
# every process the same model, so an episode seed is the same scene in every recording and evaluation.
MODEL_SEED = 0


def controller_config() -> dict:
    """robosuite's default Panda OSC_POSE controller with world-frame deltas, as robomimic's data.

    robomimic's datasets were recorded with robosuite <= 1.4, whose OSC read action deltas in the
    world frame; robosuite 1.5 defaults to the robot base frame, which differs for the second,
    rotated arm of TwoArmTransport. Each Panda gets its own copy (its single arm is "right").
    """
    config = load_composite_controller_config(robot="Panda")
    config["body_parts"]["right"]["input_ref_frame"] = "world"
    return config


class RobomimicEnv(gym.Env):
    """One robomimic task in robosuite (Panda, OSC_POSE, 20 Hz, sparse reward)."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FREQ}

    def __init__(
        self,
        task: str = "Lift",
        obs_type: str = "low_dim",
        episode_length: int | None = None,
        camera_names: list[str] | None = None,
        image_size: int | None = None,
        render_camera: str = "agentview",
        render_size: int = 256,
    ):
        super().__init__()
        check_obs_type(obs_type)
        self.task_spec = get_task(task)
        self.task = task
        self.task_description = self.task_spec.description
        self.obs_type = obs_type
        self.render_mode = "rgb_array"
        # lerobot-eval reads the rollout length from this attribute.
        self._max_episode_steps = episode_length or self.task_spec.episode_length
        self.camera_names = list(camera_names or self.task_spec.cameras)
        self.image_size = image_size or self.task_spec.image_size
        self.render_camera = render_camera
        self.render_size = render_size
        use_images = obs_type == "image"
        with seeded_context(MODEL_SEED):  # LeRobot's: seeds, then restores the caller's random state
            self._env = robosuite.make(
                self.task_spec.name,
                robots=["Panda"] * self.task_spec.n_arms,
                env_configuration=self.task_spec.env_configuration,
                controller_configs=controller_config(),
                control_freq=CONTROL_FREQ,
                horizon=self._max_episode_steps,
                ignore_done=True,  # this wrapper decides when an episode ends
                reward_shaping=False,  # robomimic's sparse task reward
                use_object_obs=True,
                use_camera_obs=use_images,
                camera_names=self.camera_names,
                camera_heights=self.image_size,
                camera_widths=self.image_size,
                has_renderer=False,
                # Low-dim envs open no GL context at all until render() asks for a video frame.
                has_offscreen_renderer=use_images,
                # Soft resets re-sample object placements without recompiling the MuJoCo model each episode.
                hard_reset=False,
            )
        self.observation_space = self._observation_space()
        low, high = self._env.action_spec
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self._raw_obs: dict | None = None
        self._steps = 0
        self._render_failed = False

    def _observation_space(self) -> spaces.Dict:
        space = {"agent_pos": spaces.Box(-np.inf, np.inf, (self.task_spec.state_dim,), np.float32)}
        if self.obs_type == "low_dim":
            space["environment_state"] = spaces.Box(-np.inf, np.inf, (self.task_spec.object_dim,), np.float32)
        else:
            shape = (self.image_size, self.image_size, 3)
            space["pixels"] = spaces.Dict(
                {cam: spaces.Box(0, 255, shape, np.uint8) for cam in self.camera_names}
            )
        return spaces.Dict(space)

    @property
    def sim_env(self):
        """The robosuite environment itself (task internals such as target placements), for scripted
        demonstrators."""
        return self._env

    @property
    def raw_observation(self) -> dict:
        """robosuite's latest observation dict (all keys, e.g. "cube_pos"), for scripted demonstrators."""
        if self._raw_obs is None:
            raise RuntimeError("No observation yet: call reset() first.")
        return self._raw_obs

    def _observation(self) -> dict:
        raw = self._raw_obs
        obs = {
            "agent_pos": np.concatenate([raw[key] for key in self.task_spec.state_keys]).astype(np.float32)
        }
        if self.obs_type == "low_dim":
            obs["environment_state"] = raw["object-state"].astype(np.float32)
        else:
            # robosuite renders OpenGL-style (bottom row first); robomimic stores images upright.
            obs["pixels"] = {
                cam: np.ascontiguousarray(raw[f"{cam}_image"][::-1]) for cam in self.camera_names
            }
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            # robosuite samples object placements and joint noise from NumPy's global generator, so
            # that is what a seed must set (robomimic's rollouts do the same).
            np.random.seed(seed)
        self._raw_obs = self._env.reset()
        self._steps = 0
        return self._observation(), {"is_success": False}

    def step(self, action: np.ndarray):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{self.task} takes actions of shape {self.action_space.shape}, got {action.shape}."
            )
        self._raw_obs, reward, _, _ = self._env.step(action)
        self._steps += 1
        success = bool(self._env._check_success())
        truncated = self._steps >= self._max_episode_steps
        return self._observation(), float(reward), success, truncated, {"is_success": success}

    def render(self) -> np.ndarray:
        """An upright RGB frame from `render_camera` (black, with one warning, if GL is unavailable)."""
        size = self.render_size
        if not self._ensure_render_context():
            return np.zeros((size, size, 3), dtype=np.uint8)
        frame = self._env.sim.render(width=size, height=size, camera_name=self.render_camera)
        return np.ascontiguousarray(frame[::-1])

    def _ensure_render_context(self) -> bool:
        """Open the offscreen GL context on first use; False if rendering is impossible here."""
        sim = self._env.sim
        if sim._render_context_offscreen is not None:
            return True
        if self._render_failed:
            return False
        try:
            MjRenderContextOffscreen(sim, device_id=-1)  # registers itself on `sim`
        except Exception as err:
            self._render_failed = True
            logger.warning(
                "Offscreen rendering is unavailable (%s): video frames will be black, "
                "metrics are unaffected. "
                "Set MUJOCO_GL=egl (libegl1) or MUJOCO_GL=osmesa (libosmesa6) to render.",
                err,
            )
            return False
        # robosuite's own defaults: visual meshes on, collision meshes off.
        sim._render_context_offscreen.vopt.geomgroup[0] = 0
        sim._render_context_offscreen.vopt.geomgroup[1] = 1
        return True

    def close(self):
        self._env.close()


def make_vector_env(n_envs: int, use_async_envs: bool, **env_kwargs) -> gym.vector.VectorEnv:
    """`n_envs` RobomimicEnvs in one vector env, frozen after their episode ends.

    The freeze (LeRobot's own wrapper) stops stepping physics and rendering for sub-envs that
    already finished while the batch waits for the slowest one; it needs NEXT_STEP autoreset.
    """
    if n_envs < 1:
        raise ValueError(f"n_envs must be at least 1, got {n_envs}.")
    fns = [freeze_after_episode_end(partial(RobomimicEnv, **env_kwargs)) for _ in range(n_envs)]
    autoreset = gym.vector.AutoresetMode.NEXT_STEP
    if use_async_envs and n_envs > 1:
        return gym.vector.AsyncVectorEnv(fns, context="forkserver", autoreset_mode=autoreset)
    return gym.vector.SyncVectorEnv(fns, autoreset_mode=autoreset)
