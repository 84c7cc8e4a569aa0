"""Streaming Diffusion Policy for LeRobot. Importing the package registers `--policy.type=sdp`."""

from .configuration_sdp import SDPConfig
from .modeling_sdp import SDPPolicy
from .processor_sdp import make_sdp_pre_post_processors

__all__ = ["SDPConfig", "SDPPolicy", "make_sdp_pre_post_processors"]
