"""Discovery shim: LeRobot imports the module named like the distribution (`lerobot_policy_sdp`)."""

import lerobot_sdp  # noqa: F401  (registers the `sdp` policy type)
