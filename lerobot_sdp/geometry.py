"""Chunk geometry of the action sequence: the one place that owns SDP's sizes.

Layout of the denoised sequence (sdp-algorithm.md, section 2; paper Sec. "Action Buffer"):

    [ To-1 past slots | chunk 0 (Tb) | chunk 1 (Tb) | ... | chunk h-1 (Tb) | r padding slots ]

Past slots belong to chunk 0, padding slots to the last chunk. Slots ``To-1 .. To-1+Tb-1`` are the
actions executed after each call. Noise levels are counted in *steps remaining* ``k`` (0 = clean,
N = pure noise); at the start of every call chunk i sits at ``k = (i+1) * N/h`` (paper Eq. 3).
"""

from dataclasses import dataclass
from functools import cached_property

import torch


@dataclass(frozen=True)
class ChunkGeometry:
    n_obs_steps: int  # To
    chunk_len: int  # Tb, LeRobot's n_action_steps
    n_chunks: int  # h
    num_inference_steps: int  # N
    downsampling: int  # the U-Net's temporal downsampling factor

    def __post_init__(self):
        for name in ("n_obs_steps", "chunk_len", "n_chunks", "num_inference_steps", "downsampling"):
            if getattr(self, name) <= 0:
                field = {"chunk_len": "n_action_steps", "downsampling": "down_dims"}.get(name, name)
                raise ValueError(f"`{field}` must be positive, got {getattr(self, name)}.")
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
        """Past slots + h chunks, rounded up to a multiple of the U-Net's downsampling factor."""
        unpadded = self.n_past + self.n_future
        return -(-unpadded // self.downsampling) * self.downsampling

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

    def describe(self) -> str:
        """The line logged when a config is built and printed by the main job."""
        return (
            f"SDP geometry: horizon={self.horizon} ({self.n_past} past + {self.n_chunks} chunks x "
            f"{self.chunk_len} + {self.n_pad} padding), {self.steps_per_call} denoiser calls per chunk"
        )
