"""The variable-noise conditional 1D U-Net.

SDP's denoiser is Diffusion Policy's U-Net with one change (paper Sec. "Action primer and noise
corruption scheme": "only modifying the diffusion step encoder to accept a unique diffusion step
for each element in the buffer"). We therefore build LeRobot's ``DiffusionConditionalUnet1d``
unchanged and replace its diffusion-step encoder with the paper-faithful per-slot encoder:
sinusoidal embedding of every slot's level -> flatten (B, T*E) -> MLP -> one (B, E) vector, which
the U-Net concatenates with the observation conditioning and applies through its usual FiLM.
The flatten ties the network to one horizon (docs/algorithm.md, section 5).

``step_conditioning="film_per_slot"`` is the alternative: LeRobot's step encoder is kept as it is
(sinusoidal + MLP, DP's weight layout) and applied to every slot's level; the U-Net's conditioning
becomes per position, (B, T, E + G) = [step_emb(t_slot), global_cond], and every residual block
applies its FiLM (its own ``cond_encoder``) per position, the conditioning average-pooled to the
block's temporal length. With every slot at one level this is exactly DP's network, at any horizon.
Both pieces are LeRobot's classes with one method overridden, swapped in place, so the state-dict
keys stay DP's.

A streaming call only ever visits s = N/h level patterns, so both step encoders keep the
embeddings of a streaming plan's timesteps (``PlanEmbeddingCache``) instead of recomputing the
sinusoidal embedding and MLP on every denoiser call.
"""

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.diffusion.modeling_diffusion import (
    DiffusionConditionalResidualBlock1d,
    DiffusionConditionalUnet1d,
    DiffusionSinusoidalPosEmb,
)
from torch import Tensor, nn


class PlanEmbeddingCache:
    """Step embeddings of a streaming plan's timesteps tensors, looked up by identity.

    The buffer passes the same s timesteps tensors (its plan's, one per step) on every call, so an
    embedding computed once serves every later call. An entry holds its tensor, so its id cannot be
    reused while cached, and is valid while the encoder's weights are the same storage at the same
    version and autocast is as it was: moving or casting the model, loading weights, an optimiser
    step or entering autocast recompute it. Only
    the plan given to ``keep`` is cached (never training batches), only without autograd, and never
    inside a compiled graph (which computes the embedding itself)."""

    def __init__(self):
        self._entries: dict[int, tuple[Tensor, Tensor | None]] = {}
        self._key: tuple | None = None

    def keep(self, encoder: nn.Module, plan_timesteps: list[Tensor]) -> None:
        """Cache these tensors' embeddings from now on (replacing another plan's); called once per
        streaming call, so that the weights and autocast are checked there, not per denoiser call."""
        key = (weights_key(encoder), autocast_key(plan_timesteps[0].device.type))
        stale = any(self._entries.get(id(t), (None,))[0] is not t for t in plan_timesteps)
        if stale or key != self._key:
            self._entries = {id(t): (t, None) for t in plan_timesteps}
            self._key = key

    def embed(self, timesteps: Tensor, compute) -> Tensor:
        if torch.compiler.is_compiling() or torch.is_grad_enabled():
            return compute(timesteps)
        entry = self._entries.get(id(timesteps))
        if entry is None or entry[0] is not timesteps:
            return compute(timesteps)
        if entry[1] is None:
            entry = self._entries[id(timesteps)] = (timesteps, compute(timesteps))
        return entry[1]


def weights_key(module: nn.Module) -> tuple:
    """Changes when a weight is moved, cast, replaced or updated in place."""
    return tuple((p.data_ptr(), p.dtype, p._version) for p in module.parameters())


def autocast_key(device_type: str) -> torch.dtype | None:
    """The dtype autocast computes in on this device (None when off): an embedding made under
    autocast is not the embedding made without it."""
    return torch.get_autocast_dtype(device_type) if torch.is_autocast_enabled(device_type) else None


def plan_embedding_cache(encoder: nn.Module) -> PlanEmbeddingCache:
    """The encoder's cache, created on first use (LeRobot's encoder gets it by a class swap)."""
    if "_plan_embeddings" not in encoder.__dict__:
        encoder.__dict__["_plan_embeddings"] = PlanEmbeddingCache()
    return encoder.__dict__["_plan_embeddings"]


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
        return plan_embedding_cache(self).embed(timesteps, self.encode)

    def encode(self, timesteps: Tensor) -> Tensor:
        return self.mlp(self.embed(timesteps).flatten(start_dim=1))


class PerSlotDPStepEncoder(nn.Sequential):
    """LeRobot's step encoder (sinusoidal, Linear, Mish, Linear) applied to every slot's level,
    (B, T) -> (B, T, E), with a streaming plan's embeddings cached."""

    def forward(self, timesteps: Tensor) -> Tensor:
        return plan_embedding_cache(self).embed(timesteps, super().forward)


class PerPositionFiLMBlock(DiffusionConditionalResidualBlock1d):
    """LeRobot's residual block whose FiLM also takes per-position conditioning (B, T, cond_dim): it is
    average-pooled to the block's temporal length and goes through the block's own ``cond_encoder``."""

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        out = self.conv1(x)
        pooled = cond  # already at this block's length at the U-Net's top level
        if out.shape[-1] != cond.shape[1]:
            pooled = F.adaptive_avg_pool1d(cond.transpose(1, 2), out.shape[-1]).transpose(1, 2)
        film = self.cond_encoder(pooled).transpose(1, 2)  # (B, channels, L)
        if self.use_film_scale_modulation:
            out = film[:, : self.out_channels] * out + film[:, self.out_channels :]
        else:
            out = out + film
        return self.conv2(out) + self.residual_conv(x)


class FiLMPerSlotUnet1d(DiffusionConditionalUnet1d):
    """LeRobot's U-Net taking one level per slot, (B, T), each slot conditioning its own position."""

    def forward(self, x: Tensor, timestep: Tensor, global_cond: Tensor | None = None) -> Tensor:
        if timestep.ndim != 2 or timestep.shape[1] != x.shape[1]:
            raise ValueError(
                f"The variable-noise U-Net needs one level per slot, shape (B, {x.shape[1]}); "
                f"got {tuple(timestep.shape)}."
            )
        if global_cond is not None:  # LeRobot's forward concatenates it with the (B, T, E) step embedding
            global_cond = global_cond.unsqueeze(1).expand(-1, x.shape[1], -1)
        return super().forward(x, timestep, global_cond=global_cond)


def make_variable_noise(unet: nn.Module, embed_dim: int, horizon: int, mode: str = "flatten") -> None:
    """Give LeRobot's U-Net (same blocks, same FiLM) a step input of one level per slot, with the
    paper's flattened step encoder (``mode="flatten"``) or per-position FiLM (``"film_per_slot"``)."""
    if not isinstance(unet, DiffusionConditionalUnet1d):
        raise TypeError(f"Expected LeRobot's DiffusionConditionalUnet1d, got {type(unet).__name__}.")
    if mode == "flatten":
        unet.diffusion_step_encoder = PerSlotStepEncoder(embed_dim, horizon)
    elif mode == "film_per_slot":
        unet.__class__ = FiLMPerSlotUnet1d
        unet.diffusion_step_encoder.__class__ = PerSlotDPStepEncoder
        for module in unet.modules():
            if type(module) is DiffusionConditionalResidualBlock1d:
                module.__class__ = PerPositionFiLMBlock
    else:
        raise ValueError(f"Unknown step conditioning {mode!r}: use 'flatten' or 'film_per_slot'.")


@torch.no_grad()
def flatten_encoder_from_dp(encoder: PerSlotStepEncoder, dp_encoder: dict[str, Tensor]) -> None:
    """Initialise the paper's flattened step encoder from the state dict of DP's (LeRobot's layout:
    0 sinusoidal, 1 Linear, 2 Mish, 3 Linear) so that with every slot at one level it computes DP's
    embedding: the first layer sees the T slots' embeddings side by side, so it gets DP's first weight
    divided by T, once per slot (their sum is DP's product); the second layer is DP's."""
    first = encoder.mlp[0]
    first.weight.copy_(dp_encoder["1.weight"].repeat(1, encoder.horizon) / encoder.horizon)
    first.bias.copy_(dp_encoder["1.bias"])
    encoder.mlp[2].load_state_dict({"weight": dp_encoder["3.weight"], "bias": dp_encoder["3.bias"]})
