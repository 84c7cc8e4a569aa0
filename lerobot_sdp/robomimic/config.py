"""`--env.type=robomimic`: the robomimic tasks (robosuite) as a LeRobot environment.

This module must stay cheap and importable without the `robomimic` extra: LeRobot imports it via the
plugin shim on every `lerobot-train` / `lerobot-eval` start. robosuite is imported only when an
environment is actually built (`create_envs`).
"""

import logging
from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from .tasks import CONTROL_FREQ, check_obs_type, get_task


@dataclass
class RobomimicEnvConfig(EnvConfig):
    """Lift, PickPlaceCan, NutAssemblySquare, TwoArmTransport or ToolHang, built as robomimic does.

    Unset fields take the task's robomimic values: `episode_length` (400; 700 for TwoArmTransport and
    ToolHang), `camera_names` and `image_size` (84 px; 240 px for ToolHang).
    """

    task: str = "Lift"
    fps: int = CONTROL_FREQ
    obs_type: str = "low_dim"
    episode_length: int | None = None
    camera_names: str | None = None  # comma-separated robosuite camera names
    image_size: int | None = None
    # lerobot-eval always renders videos of the first episodes: camera and square size of those frames.
    render_camera: str = "agentview"
    render_size: int = 256
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        spec = get_task(self.task)
        check_obs_type(self.obs_type)
        if self.fps != CONTROL_FREQ:
            raise ValueError(
                f"robomimic's controllers run at {CONTROL_FREQ} Hz, got fps={self.fps}: "
                "leave `--env.fps` unset."
            )
        if self.episode_length is None:
            self.episode_length = spec.episode_length
        if self.image_size is None:
            self.image_size = spec.image_size
        if self.camera_names is None:
            self.camera_names = ",".join(spec.cameras)
        if self.episode_length <= 0 or self.image_size <= 0 or self.render_size <= 0:
            raise ValueError("episode_length, image_size and render_size must be positive.")
        self.features, self.features_map = self._features(spec.state_dim, spec.object_dim, spec.action_dim)

    @property
    def cameras(self) -> list[str]:
        cams = [c.strip() for c in self.camera_names.split(",") if c.strip()]
        if not cams:
            raise ValueError("`--env.camera_names` is empty: name at least one robosuite camera.")
        return cams

    def _features(self, state_dim: int, object_dim: int, action_dim: int):
        """Env observation keys -> LeRobot features, the same names the recorders and converter write."""
        features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
        }
        features_map = {ACTION: ACTION, "agent_pos": OBS_STATE}
        if self.obs_type == "low_dim":
            features["environment_state"] = PolicyFeature(type=FeatureType.ENV, shape=(object_dim,))
            features_map["environment_state"] = OBS_ENV_STATE
        else:
            for cam in self.cameras:
                features[f"pixels/{cam}"] = PolicyFeature(
                    type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)
                )
                features_map[f"pixels/{cam}"] = f"{OBS_IMAGES}.{cam}"
        return features, features_map

    @property
    def gym_kwargs(self) -> dict:
        return {
            "task": self.task,
            "obs_type": self.obs_type,
            "episode_length": self.episode_length,
            "camera_names": self.cameras,
            "image_size": self.image_size,
            "render_camera": self.render_camera,
            "render_size": self.render_size,
        }

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        """{task: {0: VectorEnv}} of `n_envs` robosuite environments (imports robosuite here)."""
        from .env import make_vector_env

        return {self.task: {0: make_vector_env(n_envs, use_async_envs, **self.gym_kwargs)}}


def register(name: str = "robomimic") -> bool:
    """Register `--env.type=robomimic`. If another plugin took the name first, SDP still loads (its
    policy and pusht_sim do not depend on it) and says so, instead of failing the whole plugin import
    (which LeRobot would report as a missing `sdp` policy)."""
    try:
        EnvConfig.register_subclass(name)(RobomimicEnvConfig)
    except ValueError:
        other = EnvConfig.get_choice_class(name)
        if other is RobomimicEnvConfig:
            return True
        logging.warning(
            "lerobot_policy_sdp: --env.type=%s is already registered by %s.%s (another plugin), so SDP's "
            "robomimic environment is not available; --policy.type=sdp and --robot.type=pusht_sim are. "
            "Uninstall one of the two plugins to use the other's robomimic environment.",
            name,
            other.__module__,
            other.__qualname__,
        )
        return False
    return True


register()
