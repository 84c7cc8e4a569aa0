"""Pre/post-processors of SDP: LeRobot's default pipeline (rename, batch, device, normalise; then
unnormalise and back to CPU), exactly as Diffusion Policy uses it. The streaming buffer lives in
normalised action space, so nothing SDP-specific happens here."""

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_sdp import SDPConfig


def make_sdp_pre_post_processors(
    config: SDPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    return make_default_pre_post_processors(config, dataset_stats)
