"""Streaming Diffusion Policy for LeRobot. Importing the package registers `--policy.type=sdp` and
`--env.type=robomimic` (robosuite itself loads only when such an env is built)."""

from .configuration_sdp import SDPConfig
from .modeling_sdp import SDPPolicy
from .processor_sdp import make_sdp_pre_post_processors
from .robomimic import RobomimicEnvConfig

__all__ = ["RobomimicEnvConfig", "SDPConfig", "SDPPolicy", "make_sdp_pre_post_processors"]
