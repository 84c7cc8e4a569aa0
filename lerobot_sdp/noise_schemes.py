"""Training noise-corruption schemes: which level every slot of a training sample is noised to.

Paper Sec. "Training SDP Policy" (Eq. 5, ``L = MSE(eps^k, eps_theta(A + eps^k; O, k))`` with one
level per slot) and Fig. "Trajectory Noise Corruptions"; docs/algorithm.md, section 6:

- constant: one t ~ U{0..T-1} for the whole sequence (plain Diffusion Policy);
- linear: t rises linearly along the slots from 0 to T-1 (deterministic, as in the authors' code);
- independent: i.i.d. t ~ U{0..T-1} per slot (Diffusion Forcing style);
- independent_chunks: i.i.d. t ~ U{0..T-1} per chunk, one level for all slots of a chunk: the later
  chunk is as often cleaner than its neighbour as noisier, so it cannot always be continued from
  the cleaner one and has to read the observation (not in the paper);
- chunkwise: chunk i in the band of steps remaining [i*s+1, (i+1)*s], one offset shared by all
  chunks of the sample, so training sees exactly the staircases that streaming inference visits
  (`chunkwise_grid="sampler"`); or, as the authors' ``get_diff_steps_training`` draws it, over the
  whole training table: chunk i at t = i*T/h + o - 1, o ~ U{1..T/h} (`chunkwise_grid="training_table"`,
  T/h level staircases instead of s).

Curriculum (`NoiseCurriculum`): a sample is drawn at one constant level with probability c(step),
else from the mixture; c is 1 for the first `constant_steps` optimiser steps, then falls linearly to 0
over `ramp_steps` (a switch when 0).

Inference delay (`max_delay` > 0): each sample also draws a delay d ~ U{0..max_delay}; its d
committed slots (the actions that run while the chunk is computed, `ChunkGeometry.delayed`) are
clean inputs, and every later slot takes the level drawn for the slot d places before it.

A mixture draws one scheme *per sample* with the given weights (the authors drew one per batch;
per sample gives every batch the mixture's proportions). All levels are training timesteps, drawn
on the device the schedule's tables live on (the model's): no host round trip per training step.
Every draw takes an optional ``generator`` (the global RNG when None): under data parallelism
each rank passes its own (`data_parallel.rank_generator`).
"""

import itertools
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .geometry import ChunkGeometry
from .schedule import CLEAN, PerSlotSchedule


@dataclass
class NoiseSchemeWeights:
    """Mixture weights of the schemes (`--policy.noise_schemes.chunkwise=0.8` ...).
    Defaults: the paper's best mixture, 80% chunk-wise + 20% constant."""

    constant: float = 0.2
    linear: float = 0.0
    independent: float = 0.0
    chunkwise: float = 0.8
    independent_chunks: float = 0.0

    def __post_init__(self):
        weights = self.as_dict()
        if any(w < 0 for w in weights.values()) or sum(weights.values()) <= 0:
            raise ValueError(
                f"noise_schemes weights must be >= 0 with a positive sum, got {weights}. "
                "Set e.g. `--policy.noise_schemes.chunkwise=0.8 --policy.noise_schemes.constant=0.2`."
            )

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}


def constant_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    t = torch.randint(
        schedule.num_train_timesteps, (batch_size, 1), device=device_of(schedule), generator=generator
    )
    return t.expand(batch_size, geometry.horizon)


def linear_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    ramp = torch.linspace(0, schedule.num_train_timesteps - 1, geometry.horizon, device=device_of(schedule))
    return ramp.round().long().expand(batch_size, geometry.horizon)


def independent_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    return torch.randint(
        schedule.num_train_timesteps,
        (batch_size, geometry.horizon),
        device=device_of(schedule),
        generator=generator,
    )


def independent_chunk_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    device = device_of(schedule)
    per_chunk = torch.randint(
        schedule.num_train_timesteps, (batch_size, geometry.n_chunks), device=device, generator=generator
    )
    return per_chunk[:, geometry.slot_chunk_on(device)]


def chunkwise_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    s = geometry.steps_per_call
    device = device_of(schedule)
    # one offset shared by all chunks of a sample
    offset = torch.randint(1, s + 1, (batch_size, 1), device=device, generator=generator)
    k = geometry.slot_chunk_on(device).unsqueeze(0) * s + offset
    return schedule.train_timesteps(k)


def chunkwise_table_levels(
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Chunk-wise over all T training timesteps (the authors' draw): chunk i at t = i*T/h + o - 1,
    one o ~ U{1..T/h} shared by the chunks of a sample; never clean, as on the sampler's grid."""
    band = schedule.num_train_timesteps // geometry.n_chunks
    device = device_of(schedule)
    offset = torch.randint(1, band + 1, (batch_size, 1), device=device, generator=generator)
    return geometry.slot_chunk_on(device).unsqueeze(0) * band + offset - 1


def device_of(schedule: PerSlotSchedule) -> torch.device:
    return schedule.timestep_table.device


SCHEMES = {
    "constant": constant_levels,
    "linear": linear_levels,
    "independent": independent_levels,
    "chunkwise": chunkwise_levels,
    "independent_chunks": independent_chunk_levels,
}
# where the chunk-wise scheme takes its levels from: the sampler's N-step grid or all T timesteps
CHUNKWISE_GRIDS = {"sampler": chunkwise_levels, "training_table": chunkwise_table_levels}


@dataclass
class NoiseCurriculum:
    """Constant levels first, the mixture after (`--policy.noise_curriculum.constant_steps=2000`):
    every sample is drawn at one constant level for the first `constant_steps` optimiser steps, then
    the share of constant-level samples falls linearly to 0 over `ramp_steps` (0: a switch). All
    zero (the default): the mixture from the first step."""

    constant_steps: int = 0
    ramp_steps: int = 0

    def __post_init__(self):
        if self.constant_steps < 0 or self.ramp_steps < 0:
            raise ValueError(
                f"noise_curriculum steps must be >= 0, got constant_steps={self.constant_steps}, "
                f"ramp_steps={self.ramp_steps}."
            )

    @property
    def enabled(self) -> bool:
        return self.constant_steps + self.ramp_steps > 0

    def constant_share(self, step: Tensor) -> Tensor:
        """c(step): the probability that a sample at optimiser step ``step`` (0-d, on the device; the
        first step is 0) is drawn at one constant level instead of from the mixture."""
        if self.ramp_steps == 0:
            return (step < self.constant_steps).float()
        return (1.0 - (step - self.constant_steps).float() / self.ramp_steps).clamp(0.0, 1.0)


def sample_levels(
    weights: NoiseSchemeWeights,
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
    chunkwise_grid: str = "sampler",
    constant_share: Tensor | None = None,
) -> Tensor:
    """Training timesteps (B, horizon) from the weighted mixture: one scheme drawn per sample, the
    chunk-wise one on ``chunkwise_grid`` (`CHUNKWISE_GRIDS`). With ``constant_share`` (a curriculum's
    c(step)) each sample is then replaced by a constant-level one with that probability. Every draw
    comes from ``generator`` (the global RNG when None)."""
    draws = SCHEMES | {"chunkwise": CHUNKWISE_GRIDS[chunkwise_grid]}
    w = weights.as_dict()
    active = [name for name in SCHEMES if w[name] > 0]
    device = device_of(schedule)
    # inverse CDF against Python floats: no weights tensor to copy to the device every step
    bounds = list(itertools.accumulate(w[name] for name in active))
    u = torch.rand(batch_size, device=device, generator=generator) * bounds[-1]
    choice = torch.zeros(batch_size, dtype=torch.long, device=device)
    for bound in bounds[:-1]:
        choice += u >= bound
    levels = torch.stack([draws[name](batch_size, geometry, schedule, generator) for name in active])
    levels = levels[choice, torch.arange(batch_size, device=device)]
    if constant_share is None:
        return levels
    constant = constant_levels(batch_size, geometry, schedule, generator)
    take = torch.rand(batch_size, device=device, generator=generator) < constant_share
    return torch.where(take.unsqueeze(-1), constant, levels)


def sample_delays(
    levels: Tensor, geometry: ChunkGeometry, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor | None]:
    """``levels`` (B, T) laid out for one inference delay d ~ U{0..max_delay} per sample, and the
    committed slots (B, T) the loss leaves out. With max_delay = 0: the levels unchanged, no mask and
    no random draw (the paper's training, bit for bit)."""
    if geometry.max_delay == 0:
        return levels, None
    delay = torch.randint(
        geometry.max_delay + 1, (levels.shape[0],), device=levels.device, generator=generator
    )
    return geometry.delayed(levels, delay, clean=CLEAN), geometry.committed_mask(delay)
