"""The hardware's limit for a training step: the step's FLOPs against what this machine computes per second.

`step_flops` counts a training step's floating-point operations (forward and backward) with torch's
own `FlopCounterMode`, which counts the matrix products and convolutions (an elementwise op, a
norm or an activation counts nothing: they are the overhead above the limit). `throughput` times the
two kernels those FLOPs run in, a square GEMM and a conv1d at the U-Net's own shape, at a given
thread count and precision; the faster of the two is the machine's rate for this network, so
FLOPs / rate is the time no implementation of the step could beat on this machine. A step within
2x of it spends at most half its time outside the arithmetic.
"""

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.utils.flop_counter import FlopCounterMode

GEMM_SIZE = 1024


def step_flops(step: Callable[[], None]) -> int:
    """The FLOPs torch counts while `step()` runs (a forward and a backward)."""
    with FlopCounterMode(display=False) as counter:
        step()
    return counter.get_total_flops()


@dataclass(frozen=True)
class ConvShape:
    """A conv1d as the U-Net runs it: (batch, channels, length) in and out, `kernel` taps."""

    batch: int
    channels: int
    length: int
    kernel: int

    @property
    def flops(self) -> int:
        return 2 * self.batch * self.channels * self.length * self.channels * self.kernel


def _gflops(run: Callable[[], object], flops: int, min_seconds: float) -> float:
    """GFLOP/s of `run`, repeated for at least `min_seconds` after one warm-up call; best of 3."""
    run()
    best = float("inf")
    for _ in range(3):
        calls, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < min_seconds / 3 or calls == 0:
            run()
            calls += 1
        best = min(best, elapsed / calls)
    return flops / best / 1e9


def throughput(threads: int, dtype: torch.dtype, conv: ConvShape, min_seconds: float = 0.6) -> dict:
    """GFLOP/s of a GEMM and of the U-Net's conv1d at `threads` threads in `dtype` (thread count restored)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        generator = torch.Generator().manual_seed(0)
        a, b = (torch.randn(GEMM_SIZE, GEMM_SIZE, generator=generator).to(dtype) for _ in range(2))
        x = torch.randn(conv.batch, conv.channels, conv.length, generator=generator).to(dtype)
        w = torch.randn(conv.channels, conv.channels, conv.kernel, generator=generator).to(dtype)
        gemm = _gflops(lambda: a @ b, 2 * GEMM_SIZE**3, min_seconds)
        conv1d = _gflops(
            lambda: torch.nn.functional.conv1d(x, w, padding=conv.kernel // 2), conv.flops, min_seconds
        )
    finally:
        torch.set_num_threads(previous)
    return {"gemm_gflops": gemm, "conv1d_gflops": conv1d, "peak_gflops": max(gemm, conv1d)}
