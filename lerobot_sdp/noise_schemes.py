"""Training noise-corruption schemes: which level every slot of a training sample is noised to.

Paper Sec. "Training SDP Policy" (Eq. 5, ``L = MSE(eps^k, eps_theta(A + eps^k; O, k))`` with one
level per slot) and Fig. "Trajectory Noise Corruptions"; docs/algorithm.md, section 6:

- constant: one t ~ U{0..T-1} for the whole sequence (plain Diffusion Policy);
- linear: t rises linearly along the slots from 0 to T-1 (deterministic, as in the authors' code);
- independent: i.i.d. t ~ U{0..T-1} per slot (Diffusion Forcing style);
- chunkwise: chunk i in the band of steps remaining [i*s+1, (i+1)*s], one offset shared by all
  chunks of the sample, so training sees exactly the staircases that streaming inference visits.

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
    """Mixture weights of the four schemes (`--policy.noise_schemes.chunkwise=0.8` ...).
    Defaults: the paper's best mixture, 80% chunk-wise + 20% constant."""

    constant: float = 0.2
    linear: float = 0.0
    independent: float = 0.0
    chunkwise: float = 0.8

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


def device_of(schedule: PerSlotSchedule) -> torch.device:
    return schedule.timestep_table.device


SCHEMES = {
    "constant": constant_levels,
    "linear": linear_levels,
    "independent": independent_levels,
    "chunkwise": chunkwise_levels,
}


def sample_levels(
    weights: NoiseSchemeWeights,
    batch_size: int,
    geometry: ChunkGeometry,
    schedule: PerSlotSchedule,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Training timesteps (B, horizon) from the weighted mixture: one scheme drawn per sample. Every
    draw comes from ``generator`` (the global RNG when None)."""
    w = weights.as_dict()
    active = [name for name in SCHEMES if w[name] > 0]
    device = device_of(schedule)
    # inverse CDF against Python floats: no weights tensor to copy to the device every step
    bounds = list(itertools.accumulate(w[name] for name in active))
    u = torch.rand(batch_size, device=device, generator=generator) * bounds[-1]
    choice = torch.zeros(batch_size, dtype=torch.long, device=device)
    for bound in bounds[:-1]:
        choice += u >= bound
    levels = torch.stack([SCHEMES[name](batch_size, geometry, schedule, generator) for name in active])
    return levels[choice, torch.arange(batch_size, device=device)]


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
