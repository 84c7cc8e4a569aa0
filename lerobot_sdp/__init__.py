"""Streaming Diffusion Policy for LeRobot. Importing the package registers `--policy.type=sdp`,
`--env.type=robomimic` (robosuite itself loads only when such an env is built) and
`--robot.type=pusht_sim` (gym-pusht loads only when the robot connects), and serves datasets without
cameras from memory (`lerobot_sdp.memory_dataset`; `SDP_DATA_IN_MEMORY=0` turns that off)."""

from . import torchcodec_notice

# First, before anything builds a LeRobot dataset config: LeRobot's torchcodec fallback in one line.
torchcodec_notice.install()

from . import memory_dataset, model_card  # noqa: E402
from .configuration_sdp import SDPConfig  # noqa: E402
from .modeling_sdp import SDPPolicy  # noqa: E402
from .processor_sdp import make_sdp_pre_post_processors  # noqa: E402
from .robomimic import RobomimicEnvConfig  # noqa: E402
from .robots import PushTSimConfig  # noqa: E402

model_card.install()  # LeRobot's main branch renders model cards outside the policy class
memory_dataset.install()

__all__ = ["PushTSimConfig", "RobomimicEnvConfig", "SDPConfig", "SDPPolicy", "make_sdp_pre_post_processors"]
