"""Chunk geometry of the action sequence: the one place that owns SDP's sizes.

Layout of the denoised sequence (docs/algorithm.md, section 2; paper Sec. "Action Buffer"):

    [ To-1 past slots | chunk 0 (Tb) | chunk 1 (Tb) | ... | chunk h-1 (Tb) | r padding slots ]

Past slots belong to chunk 0, padding slots to the last chunk. Slots ``To-1 .. To-1+Tb-1`` are the
actions executed after each call. Noise levels are counted in *steps remaining* ``k`` (0 = clean,
N = pure noise); at the start of every call chunk i sits at ``k = (i+1) * N/h`` (paper Eq. 3).

Inference delay (docs/deployment.md, "Delay-aware streaming"): when a call takes d control ticks,
the d actions the robot runs meanwhile are already decided. They enter the sequence as *committed*
slots, clean (k = 0), between the past slots and chunk 0, and everything after them moves d slots
later:

    [ To-1 past slots | d committed (k = 0) | chunk 0 | ... | chunk h-1 | r - d padding slots ]

so the observation of the call's tick conditions chunks that start d ticks after it. Room for
``max_delay`` committed slots is part of the padding (the horizon grows when the padding is shorter).
"""

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor


@dataclass(frozen=True)
class ChunkGeometry:
    n_obs_steps: int  # To
    chunk_len: int  # Tb, LeRobot's n_action_steps
    n_chunks: int  # h
    num_inference_steps: int  # N
    downsampling: int  # the U-Net's temporal downsampling factor
    max_delay: int = 0  # committed slots the layout has room for (inference delay in control ticks)

    def __post_init__(self):
        for name in ("n_obs_steps", "chunk_len", "n_chunks", "num_inference_steps", "downsampling"):
            if getattr(self, name) <= 0:
                field = {"chunk_len": "n_action_steps", "downsampling": "down_dims"}.get(name, name)
                raise ValueError(f"`{field}` must be positive, got {getattr(self, name)}.")
        if self.max_delay < 0 or self.max_delay > max(0, self.chunk_len - self.n_past):
            # the committed actions and the past slots before them come from the last executed chunk
            raise ValueError(
                f"`max_delay` must be between 0 and n_action_steps - (n_obs_steps - 1) = "
                f"{max(0, self.chunk_len - self.n_past)}, got {self.max_delay}: the actions that run during "
                "inference come from the chunk being executed. Lower `max_delay` or raise `n_action_steps`."
            )
        if self.num_inference_steps % self.n_chunks != 0:
            raise ValueError(
                f"num_inference_steps={self.num_inference_steps} is not divisible by "
                f"n_chunks={self.n_chunks}: "
                "chunk noise levels would drift from call to call. Change `num_inference_steps` "
                f"(e.g. to {self.n_chunks * max(1, round(self.num_inference_steps / self.n_chunks))}) "
                "or `n_chunks`."
            )

    @property
    def n_past(self) -> int:
        return self.n_obs_steps - 1

    @property
    def n_future(self) -> int:
        return self.n_chunks * self.chunk_len

    @property
    def horizon(self) -> int:
        """Past slots + room for max_delay committed slots + h chunks, rounded up to a multiple of the
        U-Net's downsampling factor."""
        return round_up(self.n_past + self.max_delay + self.n_future, self.downsampling)

    @property
    def n_pad(self) -> int:
        return self.horizon - self.n_past - self.n_future

    @property
    def steps_per_call(self) -> int:
        """s = N / h: denoiser calls per executed chunk."""
        return self.num_inference_steps // self.n_chunks

    @property
    def executed(self) -> slice:
        return slice(self.n_past, self.n_past + self.chunk_len)

    @cached_property
    def slot_chunk(self) -> torch.Tensor:
        """(horizon,) chunk index of every slot: past slots -> 0, padding -> h-1."""
        future = torch.arange(self.n_future) // self.chunk_len
        return torch.cat(
            [
                torch.zeros(self.n_past, dtype=torch.long),
                future,
                torch.full((self.n_pad,), self.n_chunks - 1, dtype=torch.long),
            ]
        )

    def slot_chunk_on(self, device: torch.device) -> torch.Tensor:
        """`slot_chunk` on `device`, copied there once: training draws levels on the device every step."""
        copies = self.__dict__.setdefault("_slot_chunk_copies", {})
        if device not in copies:
            copies[device] = self.slot_chunk.to(device)
        return copies[device]

    @cached_property
    def start_levels(self) -> torch.Tensor:
        """(horizon,) steps remaining of every slot at the start of a streaming call."""
        return (self.slot_chunk + 1) * self.steps_per_call

    def delayed(self, levels: Tensor, delay: Tensor, clean: int) -> Tensor:
        """The layout at inference delay ``delay`` ((B,) ticks, each <= max_delay) from the undelayed
        ``levels`` (B, T): past slots keep theirs, the ``delay`` slots after them are committed
        (``clean``: k = 0 or the clean timestep -1), every later slot takes the level of the slot
        ``delay`` places before it. With delay 0 this is ``levels`` unchanged."""
        j = torch.arange(self.horizon, device=levels.device)
        d = delay.unsqueeze(-1)
        committed = self.committed_mask(delay)
        source = torch.where(j >= self.n_past + d, j - d, j)
        return torch.where(committed, clean, levels.gather(-1, source.expand_as(levels)))

    def committed_mask(self, delay: Tensor) -> Tensor:
        """(B, T) True on the committed slots of each delay in ``delay`` (B,)."""
        j = torch.arange(self.horizon, device=delay.device)
        d = delay.unsqueeze(-1)
        return (j >= self.n_past) & (j < self.n_past + d)

    def describe(self) -> str:
        """The line logged when a config is built and printed by the main job."""
        delay = f" + room for {self.max_delay} committed" if self.max_delay else ""
        return (
            f"SDP geometry: horizon={self.horizon} ({self.n_past} past{delay} + {self.n_chunks} chunks x "
            f"{self.chunk_len} + {self.n_pad - self.max_delay} padding), "
            f"{self.steps_per_call} denoiser calls per chunk"
        )


def round_up(length: int, multiple: int) -> int:
    """The smallest multiple of ``multiple`` that is at least ``length`` (a U-Net's sequence length)."""
    return -(-length // multiple) * multiple
