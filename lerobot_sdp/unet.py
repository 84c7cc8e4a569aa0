"""The variable-noise conditional 1D U-Net.

SDP's denoiser is Diffusion Policy's U-Net with one change (paper Sec. "Action primer and noise
corruption scheme": "only modifying the diffusion step encoder to accept a unique diffusion step
for each element in the buffer"). We therefore build LeRobot's ``DiffusionConditionalUnet1d``
unchanged and replace its diffusion-step encoder with the paper-faithful per-slot encoder:
sinusoidal embedding of every slot's level -> flatten (B, T*E) -> MLP -> one (B, E) vector, which
the U-Net concatenates with the observation conditioning and applies through its usual FiLM.
The flatten ties the network to one horizon (sdp-algorithm.md, section 5).
"""

from lerobot.policies.diffusion.modeling_diffusion import (
    DiffusionConditionalUnet1d,
    DiffusionSinusoidalPosEmb,
)
from torch import Tensor, nn


class PerSlotStepEncoder(nn.Module):
    """(B, T) training timesteps -> (B, E) conditioning vector."""

    def __init__(self, embed_dim: int, horizon: int):
        super().__init__()
        self.horizon = horizon
        self.embed = DiffusionSinusoidalPosEmb(embed_dim)
        self.mlp = nn.Sequential(
            nn.Linear(horizon * embed_dim, embed_dim * 4),
            nn.Mish(),
            nn.Linear(embed_dim * 4, embed_dim),
        )

    def forward(self, timesteps: Tensor) -> Tensor:
        if timesteps.ndim != 2 or timesteps.shape[1] != self.horizon:
            raise ValueError(
                f"The variable-noise U-Net needs one level per slot, shape (B, {self.horizon}); "
                f"got {tuple(timesteps.shape)}."
            )
        return self.mlp(self.embed(timesteps).flatten(start_dim=1))


def make_variable_noise(unet: nn.Module, embed_dim: int, horizon: int) -> None:
    """Give LeRobot's U-Net (same blocks, same FiLM) a step input of one level per slot. Works on a
    ``torch.compile``d U-Net too: compilation is lazy, so the swap happens before tracing."""
    base = getattr(unet, "_orig_mod", unet)
    if not isinstance(base, DiffusionConditionalUnet1d):
        raise TypeError(f"Expected LeRobot's DiffusionConditionalUnet1d, got {type(base).__name__}.")
    base.diffusion_step_encoder = PerSlotStepEncoder(embed_dim, horizon)
