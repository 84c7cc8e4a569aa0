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
from typing import NamedTuple

import torch
from torch import Tensor

from .geometry import ChunkGeometry
from .schedule import PerSlotSchedule, StepCoefficients, gaussian_like

# (noisy sequence (B, T, A), training timesteps (B, T)) -> model output (B, T, A)
Denoiser = Callable[[Tensor, Tensor], Tensor]


class StreamNoise(NamedTuple):
    """Every random draw of one streaming call, drawn before it runs: the call itself is then a pure
    tensor function (compilable, capturable as a CUDA graph) and one generator reproduces it."""

    steps: Tensor | None  # (s, B, T, A) DDPM step noise; None for deterministic DDIM
    shift: Tensor  # (B, T, A): the re-noise of the past slots, then the appended tail


# (buffer sample, plan, noise) -> (executed chunk, next buffer sample): one streaming call
StreamStep = Callable[[Tensor, list[StepCoefficients], StreamNoise], tuple[Tensor, Tensor]]


def reverse_plan(
    schedule: PerSlotSchedule, k_start: Tensor, n_steps: int, batch_size: int
) -> list[StepCoefficients]:
    """Coefficients of ``n_steps`` reverse steps starting from per-slot steps-remaining ``k_start``
    (T,); the timesteps are expanded to (batch_size, T) once here, so that every call hands the
    denoiser the same tensors (the step encoder caches their embeddings, `unet.PlanEmbeddingCache`)."""
    k_min = int(k_start.min())  # one read per plan: which steps leave some slot clean
    plan = [schedule.coefficients((k_start - j).clamp(min=0), all_active=k_min > j) for j in range(n_steps)]
    return [c._replace(timesteps=c.timesteps.expand(batch_size, -1)) for c in plan]


def step_noise(
    plan: list[StepCoefficients], like: Tensor, generator: torch.Generator | None
) -> Tensor | None:
    """DDPM's step noise for every step of ``plan`` (len(plan), *like.shape); None when it adds none."""
    if plan[0].noise_std is None:
        return None
    return gaussian_like(like.expand(len(plan), *like.shape), generator)


def run_reverse_steps(
    schedule: PerSlotSchedule,
    denoiser: Denoiser,
    sample: Tensor,
    plan: list[StepCoefficients],
    noise: Tensor | None,
) -> Tensor:
    """One denoiser call and one per-slot reverse step per entry of ``plan``, ``noise[j]`` being
    DDPM's step noise of step j."""
    for j, c in enumerate(plan):
        model_output = denoiser(sample, c.timesteps)
        sample = schedule.apply_step(c, model_output, sample, noise=None if noise is None else noise[j])
    return sample


def shift(geometry: ChunkGeometry, sample: Tensor, start: StepCoefficients, noise: Tensor) -> Tensor:
    """Pop chunk 0 and roll: kept chunks move down one place, the executed actions now in the past
    slots are re-noised to chunk 0's start level (``start``), a chunk of N(0, I) and the padding are
    appended at level N. ``noise`` (B, T, A) supplies both draws."""
    g = geometry
    kept = sample[:, g.chunk_len : g.n_past + g.n_future]  # past slots, then chunks 1..h-1
    past, rest = kept[:, : g.n_past], kept[:, g.n_past :]
    a, b = start.sqrt_abar[..., : g.n_past, :], start.sqrt_one_minus_abar[..., : g.n_past, :]  # (..., T, 1)
    past = a * past + b * noise[:, : g.n_past]
    tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]
    return torch.cat([past, rest, tail], dim=1)


def stream_step(
    schedule: PerSlotSchedule,
    geometry: ChunkGeometry,
    denoiser: Denoiser,
    sample: Tensor,
    plan: list[StepCoefficients],
    noise: StreamNoise,
) -> tuple[Tensor, Tensor]:
    """Algorithm 1's loop body: s denoiser calls make chunk 0 clean; returns it (B, Tb, A) and the
    shifted buffer. No host syncs and no random draws: what runs per chunk, ready to compile."""
    sample = run_reverse_steps(schedule, denoiser, sample, plan, noise.steps)
    return sample[:, geometry.executed], shift(geometry, sample, plan[0], noise.shift)


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

    def plan(self, device: torch.device, batch_size: int) -> list[StepCoefficients]:
        """The s reverse steps every call runs, built once per device and batch size."""
        built = self._plan[0].timesteps if self._plan else None
        if built is None or built.device != device or built.shape[0] != batch_size:
            k_start = self.geometry.start_levels.to(device)
            self._plan = reverse_plan(self.schedule, k_start, self.geometry.steps_per_call, batch_size)
        return self._plan

    def prime(self, primer: Tensor, generator: torch.Generator | None = None) -> None:
        """Noise a clean (normalised) primer sequence (B, T, A) to the start levels (paper Eq. 4)."""
        t = self.plan(primer.device, primer.shape[0])[0].timesteps
        self.sample = self.schedule.add_noise(primer, gaussian_like(primer, generator), t)

    def advance(self, denoiser: Denoiser, generator: torch.Generator | None = None) -> Tensor:
        """Run s calls of a denoiser of (sample, timesteps (B, T)), pop the now clean chunk (B, Tb, A)
        and roll the buffer forward (the plain form of `run`, which the policy calls with its
        compiled or cached step). Every random draw (DDPM step noise, re-noised past slots, the new
        tail) uses ``generator``."""

        def step(sample: Tensor, plan: list[StepCoefficients], noise: StreamNoise) -> tuple[Tensor, Tensor]:
            return stream_step(self.schedule, self.geometry, denoiser, sample, plan, noise)

        return self.run(step, generator)

    def run(self, step: StreamStep, generator: torch.Generator | None = None) -> Tensor:
        """One streaming call through ``step`` (e.g. the policy's cached or compiled one): draw its
        noise, run it, keep the shifted buffer. If ``step`` raises, the buffer is left as it was."""
        if self.sample is None:
            raise RuntimeError("The streaming buffer is empty: call prime() after reset().")
        plan = self.plan(self.sample.device, self.sample.shape[0])
        noise = StreamNoise(step_noise(plan, self.sample, generator), gaussian_like(self.sample, generator))
        chunk, self.sample = step(self.sample, plan, noise)
        return chunk
