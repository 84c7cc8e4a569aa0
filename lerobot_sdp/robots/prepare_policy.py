"""`python -m lerobot_sdp.robots.prepare_policy POLICY_DIR...`: let a keypoints checkpoint whose saved
preprocessor lacks SDP's `sdp_split_state` step run on a robot that sends one joined `observation.state`
(`pusht_sim`): LeRobot Diffusion Policy checkpoints trained on keypoints (the comparisons in
docs/deployment.md), and SDP checkpoints saved before the step existed. Adds the step in place."""

import argparse
from pathlib import Path

from ..processor_sdp import add_split_state_step


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m lerobot_sdp.robots.prepare_policy",
        description="Add SDP's SplitStateStep to saved SDP checkpoints (for lerobot-rollout on a robot).",
    )
    parser.add_argument("policy_dirs", nargs="+", type=Path, help="pretrained_model folders")
    for policy_dir in parser.parse_args(argv).policy_dirs:
        changed = add_split_state_step(policy_dir)
        print(f"{policy_dir}: {'added sdp_split_state' if changed else 'already there or not needed'}")


if __name__ == "__main__":
    main()
