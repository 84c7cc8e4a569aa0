"""The streaming action buffer (paper Sec. "Action Buffer", Algorithm 1, Eq. 3-4 and the action
primers of Sec. "Initializing the action buffer"; sdp-algorithm.md, section 7).

The buffer holds one partially denoised action sequence per environment, normalised, shape
(B, horizon, A). At the start of every call its slots sit at ``geometry.start_levels`` (chunk i at
(i+1)*s steps remaining). ``advance`` runs exactly s = N/h denoiser calls, which makes chunk 0
clean, pops it, and shifts: the old chunks move down one place (each now one band cleaner, which is
exactly the start pattern), a chunk of N(0, I) is appended at level N, and the past-action slots,
now holding actions already executed, are re-noised to chunk 0's level, because training corrupts
past slots at chunk 0's level too (the authors' code left them clean but labelled noisy).
"""

from collections.abc import Callable

import torch
from torch import Tensor

from .geometry import ChunkGeometry
from .schedule import PerSlotSchedule, StepCoefficients, gaussian_like

# (noisy sequence (B, T, A), training timesteps (B, T)) -> model output (B, T, A)
Denoiser = Callable[[Tensor, Tensor], Tensor]


def reverse_plan(schedule: PerSlotSchedule, k_start: Tensor, n_steps: int) -> list[StepCoefficients]:
    """Coefficients of ``n_steps`` reverse steps starting from per-slot steps-remaining ``k_start``."""
    return [schedule.coefficients((k_start - j).clamp(min=0)) for j in range(n_steps)]


def run_reverse_steps(
    schedule: PerSlotSchedule,
    denoiser: Denoiser,
    sample: Tensor,
    plan: list[StepCoefficients],
    generator: torch.Generator | None = None,
) -> Tensor:
    """One denoiser call and one per-slot reverse step per entry of ``plan``."""
    batch = sample.shape[0]
    for c in plan:
        model_output = denoiser(sample, c.timesteps.expand(batch, -1))
        sample = schedule.apply_step(c, model_output, sample, generator=generator)
    return sample


class StreamingBuffer:
    """Persistent buffer of future actions at increasing noise levels. Plain object state: it is
    never part of the model's state dict and is dropped by ``clear`` (episode end, batch change)."""

    def __init__(self, geometry: ChunkGeometry, schedule: PerSlotSchedule):
        self.geometry = geometry
        self.schedule = schedule
        self.sample: Tensor | None = None
        self._plan: list[StepCoefficients] = []  # the s steps of a call, same every call

    @property
    def batch_size(self) -> int | None:
        return None if self.sample is None else self.sample.shape[0]

    def clear(self) -> None:
        self.sample = None

    def _call_plan(self, device: torch.device) -> list[StepCoefficients]:
        if not self._plan or self._plan[0].timesteps.device != device:
            k_start = self.geometry.start_levels.to(device)
            self._plan = reverse_plan(self.schedule, k_start, self.geometry.steps_per_call)
        return self._plan

    def prime(self, primer: Tensor, generator: torch.Generator | None = None) -> None:
        """Noise a clean (normalised) primer sequence (B, T, A) to the start levels (paper Eq. 4)."""
        t = self._call_plan(primer.device)[0].timesteps.expand(primer.shape[0], -1)
        self.sample = self.schedule.add_noise(primer, gaussian_like(primer, generator), t)

    def advance(self, denoiser: Denoiser, generator: torch.Generator | None = None) -> Tensor:
        """Run s denoiser calls, pop the now clean chunk (B, Tb, A) and roll the buffer forward.
        Every random draw (DDPM step noise, re-noised past slots, the new tail) uses ``generator``."""
        if self.sample is None:
            raise RuntimeError("The streaming buffer is empty: call prime() after reset().")
        plan = self._call_plan(self.sample.device)
        sample = run_reverse_steps(self.schedule, denoiser, self.sample, plan, generator)
        chunk = sample[:, self.geometry.executed]
        self.sample = self._shift(sample, plan[0], generator)
        return chunk

    def _shift(self, sample: Tensor, start: StepCoefficients, generator: torch.Generator | None) -> Tensor:
        g = self.geometry
        kept = sample[:, g.chunk_len : g.n_past + g.n_future]  # past slots, then chunks 1..h-1
        past, rest = kept[:, : g.n_past], kept[:, g.n_past :]
        # re-noise the executed actions now in the past slots to chunk 0's start level
        a, b = start.sqrt_abar[: g.n_past], start.sqrt_one_minus_abar[: g.n_past]
        past = a * past + b * gaussian_like(past, generator)
        # the new last chunk and the padding start at level N: pure noise
        tail = gaussian_like(sample[:, : g.chunk_len + g.n_pad], generator)
        return torch.cat([past, rest, tail], dim=1)
