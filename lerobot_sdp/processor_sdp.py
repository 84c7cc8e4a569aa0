"""Pre/post-processors of SDP: LeRobot's default pipeline (rename, batch, device, normalise; then
unnormalise and back to CPU), exactly as Diffusion Policy uses it. The streaming buffer lives in
normalised action space, so nothing SDP-specific happens here. A warm start (`init_from`) normalises
with the Diffusion Policy checkpoint's statistics, which its weights were trained with
(`warm_start.merged_stats`).

One step is added for robots: LeRobot's robot path (`lerobot-rollout`, `lerobot-record`) gathers every
scalar feature of a robot into one `observation.state` vector, so a robot cannot deliver a separate
`observation.environment_state`. For a policy that takes both, `SplitStateStep` splits such a joined
vector (robot state first, then environment state) back into the two features; it does nothing when
`observation.environment_state` is present (training, `lerobot-eval`). Checkpoints saved before the
step existed get it with `python -m lerobot_sdp.robots.prepare_policy POLICY_DIR` (`add_split_state_step`)."""

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lerobot.configs import PipelineFeatureType, PolicyFeature, PreTrainedConfig
from lerobot.processor import (
    ObservationProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    RenameObservationsProcessorStep,
)
from lerobot.processor.converters import batch_to_transition, transition_to_batch
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

from .configuration_sdp import SDPConfig
from .warm_start import PREPROCESSOR_NAME as PREPROCESSOR_FILE
from .warm_start import merged_stats


@ProcessorStepRegistry.register(name="sdp_split_state")
@dataclass
class SplitStateStep(ObservationProcessorStep):
    """`observation.state` of `state_dim + env_state_dim` values (a robot's joined scalar features)
    -> `observation.state` (the first `state_dim`) and `observation.environment_state` (the rest)."""

    state_dim: int = 0
    env_state_dim: int = 0

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        if OBS_ENV_STATE in observation or OBS_STATE not in observation:
            return observation
        state = observation[OBS_STATE]
        if state.shape[-1] != self.state_dim + self.env_state_dim:
            raise ValueError(
                f"`{OBS_STATE}` has {state.shape[-1]} values and there is no `{OBS_ENV_STATE}`: this policy "
                f"takes {self.state_dim} state values and {self.env_state_dim} environment-state values, "
                f"joined they are {self.state_dim + self.env_state_dim} (robot state first)."
            )
        observation[OBS_STATE] = state[..., : self.state_dim]
        observation[OBS_ENV_STATE] = state[..., self.state_dim :]
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"state_dim": self.state_dim, "env_state_dim": self.env_state_dim}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


def split_state_step(config: SDPConfig) -> SplitStateStep | None:
    """The step for `config`, or None when the policy takes no separate environment state."""
    if config.robot_state_feature is None or config.env_state_feature is None:
        return None
    return SplitStateStep(
        state_dim=config.robot_state_feature.shape[0], env_state_dim=config.env_state_feature.shape[0]
    )


def make_sdp_pre_post_processors(
    config: SDPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    if config.init_from:  # a warm start normalises as the Diffusion Policy its weights come from
        dataset_stats = merged_stats(config.init_from, dataset_stats)
    s = make_default_policy_processor_steps(config, dataset_stats)
    split = [step] if (step := split_state_step(config)) is not None else []
    return make_policy_processor_pipelines(
        input_steps=[s.rename_observations, *split, s.add_batch_dim, s.to_device, s.normalize],
        output_steps=[s.unnormalize, s.to_cpu],
    )


def lacks_split_state_step(policy_dir: str | Path, config: PreTrainedConfig) -> bool:
    """Whether this saved policy takes a separate environment state and its preprocessor has no
    `SplitStateStep` yet (a checkpoint saved before the step existed cannot run on a robot)."""
    if split_state_step(config) is None:
        return False
    steps = json.loads((Path(policy_dir) / PREPROCESSOR_FILE).read_text())["steps"]
    return not any(s.get("registry_name") == "sdp_split_state" for s in steps)


def add_split_state_step(policy_dir: str | Path) -> bool:
    """Insert `SplitStateStep` (after the rename step) into a saved policy's preprocessor, so that a
    checkpoint saved before the step existed runs on a robot. False when there is nothing to do."""
    policy_dir = Path(policy_dir)
    config = PreTrainedConfig.from_pretrained(policy_dir)
    if not lacks_split_state_step(policy_dir, config):
        return False
    step = split_state_step(config)
    old = json.loads((policy_dir / PREPROCESSOR_FILE).read_text())
    pre = PolicyProcessorPipeline.from_pretrained(
        policy_dir,
        config_filename=PREPROCESSOR_FILE,
        to_transition=batch_to_transition,
        to_output=transition_to_batch,
    )
    renames = [i for i, s in enumerate(pre.steps) if isinstance(s, RenameObservationsProcessorStep)]
    pre.steps.insert(renames[0] + 1 if renames else 0, step)
    pre.save_pretrained(policy_dir)
    # the state files are named by step index: drop the ones the new JSON no longer names
    new = json.loads((policy_dir / PREPROCESSOR_FILE).read_text())
    stale = {s.get("state_file") for s in old["steps"]} - {s.get("state_file") for s in new["steps"]}
    for name in stale - {None}:
        (policy_dir / name).unlink(missing_ok=True)
    return True
