"""Training noise under data parallelism (`accelerate launch`, `torchrun`): one random stream per rank.

LeRobot seeds every process alike (`set_seed(cfg.seed)` on every rank, accelerate's seeding without
`device_specific`), so that all ranks shuffle the dataset with one permutation and accelerate shards
it disjointly. SDP's training draws (the noise scheme, the per-slot levels, the delays, the Gaussian
noise; paper Eq. 5) taken from that shared global stream would then be the same on every rank: each
rank would noise its own samples with the other ranks' levels and noise, and a global batch of 2B
would hold B noise draws. So under torch.distributed with more than one process, every rank draws
its training noise from a generator of its own, seeded from one draw of the shared global stream
and the rank. The draw makes it reproducible: the same command draws the same noise, and a resumed
run (LeRobot restores the global RNG from the checkpoint) draws from where the restored stream
leads. One process keeps the global stream, bit for bit as before.
"""

import torch
import torch.distributed as dist


def world() -> tuple[int, int]:
    """(rank, number of processes) of this process; (0, 1) without torch.distributed."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def rank_generator(device: torch.device) -> torch.Generator | None:
    """This rank's generator for training noise, or None (the global RNG) in a single process.

    Seeds ``base * world_size + rank``, ``base`` drawn from the global stream: distinct for every
    rank even where the ranks' global streams had drifted apart before the call."""
    rank, size = world()
    if size == 1:
        return None
    base = int(torch.randint(2**31 - 1, ()))
    return torch.Generator(device=device).manual_seed(base * size + rank)
