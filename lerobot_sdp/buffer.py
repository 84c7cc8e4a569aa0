"""The streaming action buffer (paper Sec. "Action Buffer", Algorithm 1, Eq. 3-4 and the action
primers of Sec. "Initializing the action buffer"; docs/algorithm.md, section 7).

The buffer holds one partially denoised action sequence per environment, normalised, shape
(B, horizon, A). At the start of every call its slots sit at ``geometry.start_levels`` (chunk i at
(i+1)*s steps remaining). One streaming call (``stream_step``: the maths as a function here, the
buffer's method of that name keeping the state, the model's binding the observation) runs exactly
s = N/h denoiser calls, which makes chunk 0 clean, pops it, and shifts: the old chunks move down one
place (each now one band cleaner, which is exactly the start pattern), a chunk of N(0, I) is
appended at level N, and the past-action slots, now holding actions already executed, are re-noised
to chunk 0's level, because training corrupts past slots at chunk 0's level too (the authors' code
left them clean but labelled noisy).

A call made while d actions of the last chunk are still to run (inference delay, `ChunkGeometry`'s
committed slots) denoises a *window*: those d actions inserted clean after the past slots, the past
slots holding the actions before them, the buffer's chunks after them. Its chunk 0 then starts d
ticks after the observation, exactly where the committed actions end; the shift works on the window
without its first d slots, so the next buffer has the same layout either way.
"""

import functools
import threading
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


# (window, plan, noise, committed slots) -> (executed chunk, next buffer sample): one streaming call
StreamStep = Callable[[Tensor, list[StepCoefficients], StreamNoise, int], tuple[Tensor, Tensor]]


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


def renoise_past(geometry: ChunkGeometry, start: StepCoefficients, clean: Tensor, noise: Tensor) -> Tensor:
    """Executed actions (B, To-1, A) noised to the past slots' start level (chunk 0's, ``start``)."""
    g = geometry
    a, b = start.sqrt_abar[..., : g.n_past, :], start.sqrt_one_minus_abar[..., : g.n_past, :]  # (..., T, 1)
    return a * clean + b * noise


def shift(geometry: ChunkGeometry, sample: Tensor, start: StepCoefficients, noise: Tensor) -> Tensor:
    """Pop chunk 0 and roll: kept chunks move down one place, the executed actions now in the past
    slots are re-noised to chunk 0's start level (``start``), a chunk of N(0, I) and the padding are
    appended at level N. ``noise`` (B, T, A) supplies both draws."""
    g = geometry
    kept = sample[:, g.chunk_len : g.n_past + g.n_future]  # past slots, then chunks 1..h-1
    past, rest = kept[:, : g.n_past], kept[:, g.n_past :]
    past = renoise_past(g, start, past, noise[:, : g.n_past])
    tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]
    return torch.cat([past, rest, tail], dim=1)


def stream_step(
    schedule: PerSlotSchedule,
    geometry: ChunkGeometry,
    denoiser: Denoiser,
    window: Tensor,
    plan: list[StepCoefficients],
    noise: StreamNoise,
    committed: int = 0,
) -> tuple[Tensor, Tensor]:
    """Algorithm 1's loop body: s denoiser calls make chunk 0 clean; returns it (B, Tb, A) and the
    shifted buffer. ``committed`` slots after the past ones are clean and stay so (their level is 0
    in ``plan``); chunk 0 follows them. No host syncs and no random draws: what runs per chunk,
    ready to compile."""
    sample = run_reverse_steps(schedule, denoiser, window, plan, noise.steps)[:, committed:]
    return sample[:, geometry.executed], shift(geometry, sample, plan[0], noise.shift)


def bind(schedule: PerSlotSchedule, geometry: ChunkGeometry, denoiser: Denoiser) -> StreamStep:
    """`stream_step` over a plain denoiser of (sample, timesteps (B, T)), as the buffer calls it."""
    return functools.partial(stream_step, schedule, geometry, denoiser)


STREAM_RESET = (
    "The stream was reset (an episode's end, a client's Ready) during this call: its chunk belongs to the "
    "episode that ended and is dropped; the next call starts the new episode's stream."
)


class StreamResetError(RuntimeError):
    """A call that began before a `clear` from another thread: its stream is gone."""


class StreamingBuffer:
    """Persistent buffer of future actions at increasing noise levels. Plain object state: it is
    never part of the model's state dict and is dropped by ``clear`` (episode end, batch change)."""

    def __init__(self, geometry: ChunkGeometry, schedule: PerSlotSchedule):
        self.geometry = geometry
        self.schedule = schedule
        self.sample: Tensor | None = None
        self.last_chunk: Tensor | None = None  # (B, Tb, A) what the last call returned, clean
        self._past_noise: Tensor | None = None  # the draw that re-noised its end into the past slots
        self._plans: dict[int, list[StepCoefficients]] = {}  # committed slots -> the s steps of a call
        self._generation = 0  # counts clear()s: a call that started before one keeps nothing
        self._lock = threading.Lock()  # clear() may come from another thread than the call

    @property
    def batch_size(self) -> int | None:
        return None if self.sample is None else self.sample.shape[0]

    @property
    def generation(self) -> int:
        """How many times the buffer was cleared: a call reads it first and hands it to `prime` and
        `stream_step`, so that a `clear` from another thread in between makes the call keep nothing."""
        return self._generation

    def clear(self) -> None:
        with self._lock:
            self.sample = self.last_chunk = self._past_noise = None
            self._generation += 1

    def plan(self, device: torch.device, batch_size: int, committed: int = 0) -> list[StepCoefficients]:
        """The s reverse steps of a call with ``committed`` slots, built once per device and batch size."""
        built = next(iter(self._plans.values()))[0].timesteps if self._plans else None
        if built is not None and (built.device != device or built.shape[0] != batch_size):
            self._plans = {}
        if committed not in self._plans:
            k_start = self.geometry.start_levels.to(device)
            if committed:
                delay = torch.tensor([committed], device=device)
                k_start = self.geometry.delayed(k_start.unsqueeze(0), delay, clean=0)[0]
            self._plans[committed] = reverse_plan(
                self.schedule, k_start, self.geometry.steps_per_call, batch_size
            )
        return self._plans[committed]

    def prime(
        self, primer: Tensor, generator: torch.Generator | None = None, generation: int | None = None
    ) -> None:
        """Noise a clean (normalised) primer sequence (B, T, A) to the start levels (paper Eq. 4). With
        ``generation`` (read before the primer was computed), a buffer cleared since stays cleared."""
        t = self.plan(primer.device, primer.shape[0])[0].timesteps
        sample = self.schedule.add_noise(primer, gaussian_like(primer, generator), t)
        with self._lock:
            if generation is not None and generation != self._generation:
                raise StreamResetError(STREAM_RESET)
            self.sample, self.last_chunk, self._past_noise = sample, None, None

    def window(self, committed: int) -> Tensor:
        """What a call with ``committed`` actions of the last chunk still to run denoises: the buffer
        with those actions inserted clean after the past slots, which hold the actions before them
        (noised with the draw the shift used), and the chunks moved ``committed`` slots later into
        the padding. With 0 it is the buffer itself."""
        g, d = self.geometry, committed
        if d == 0:
            return self.sample
        if not 0 < d <= g.max_delay:
            raise ValueError(
                f"{d} committed actions, but this policy's layout has room for max_delay={g.max_delay}: "
                "train with `--policy.max_delay` at least the inference delay in control ticks."
            )
        if self.last_chunk is None:
            raise ValueError(
                f"{d} committed actions, but no chunk has run since the stream started: an episode's "
                "first chunk starts right after its observation (committed=0)."
            )
        tb, start = g.chunk_len, self.plan(self.sample.device, self.sample.shape[0])[0]
        past = renoise_past(g, start, self.last_chunk[:, tb - d - g.n_past : tb - d], self._past_noise)
        chunks = self.sample[:, g.n_past : g.horizon - d]
        return torch.cat([past, self.last_chunk[:, tb - d :], chunks], dim=1)

    def stream_step(
        self,
        step: StreamStep,
        generator: torch.Generator | None = None,
        committed: int = 0,
        generation: int | None = None,
    ) -> Tensor:
        """One streaming call: draw its noise (every draw from ``generator``), run ``step`` on the
        ``window`` of ``committed`` slots, keep the shifted buffer, return the clean chunk (B, Tb, A).
        ``step`` is `stream_step` with its schedule, geometry and denoiser bound (`bind`), or the
        model's conditioned, cached or compiled form of it. If ``step`` raises, the buffer is left as
        it was. If ``clear`` ran meanwhile, or since ``generation`` was read, it stays cleared and the
        call raises `StreamResetError`: its chunk belongs to the episode that ended (LeRobot's RTC
        engine would queue it in the next one)."""
        with self._lock:
            if generation is not None and generation != self._generation:
                raise StreamResetError(STREAM_RESET)
            if self.sample is None:
                raise RuntimeError("The streaming buffer is empty: call prime() after reset().")
            generation, window = self._generation, self.window(committed)
        plan = self.plan(window.device, window.shape[0], committed)
        noise = StreamNoise(step_noise(plan, window, generator), gaussian_like(window, generator))
        chunk, sample = step(window, plan, noise, committed)
        with self._lock:
            if generation != self._generation:  # its chunk would run in the episode that followed
                raise StreamResetError(STREAM_RESET)
            self.sample, self.last_chunk = sample, chunk
            self._past_noise = noise.shift[:, : self.geometry.n_past]
        return chunk
