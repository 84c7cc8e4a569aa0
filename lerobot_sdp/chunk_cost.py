"""What one streamed action chunk of a policy costs: denoiser calls counted with forward hooks (never
inferred from the config) and their wall time.

`stream_cost` measures a trained policy through `select_action` on the CPU after the first chunk
(SDP's primer); `CallProbe` and `denoisers` are the hooks the latency benchmarks use too.
"""

import time
from collections.abc import Iterable
from pathlib import Path
from typing import Self

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel
from lerobot.policies.factory import get_policy_class
from torch import nn


class CallProbe:
    """Counts and times the forward calls of some modules through forward hooks (counted, never
    inferred). On CUDA the intervals are CUDA events, read only after the clock has synchronised, so
    probing adds no synchronisation of its own. Use as a context manager (removes the hooks)."""

    def __init__(self, modules: Iterable[nn.Module], device: torch.device):
        self._cuda = device.type == "cuda"
        self._intervals: list[list] = []
        self._handles = []
        for module in modules:
            self._handles.append(module.register_forward_pre_hook(self._start))
            self._handles.append(module.register_forward_hook(self._stop))

    def _marker(self):
        if not self._cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def _start(self, module, args) -> None:
        self._intervals.append([self._marker(), None])

    def _stop(self, module, args, output) -> None:
        self._intervals[-1][1] = self._marker()

    @property
    def calls(self) -> int:
        return len(self._intervals)

    def seconds(self) -> float:
        if self._cuda:
            return sum(start.elapsed_time(stop) for start, stop in self._intervals) / 1000
        return sum(stop - start for start, stop in self._intervals)

    def reset(self) -> None:
        self._intervals.clear()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        for handle in self._handles:
            handle.remove()


def denoisers(policy: nn.Module) -> list[nn.Module]:
    """The U-Nets (EMA copy included), as attributes: a compiled U-Net is hooked on its wrapper."""
    return [m.unet for m in policy.modules() if isinstance(m, DiffusionModel)]


def load_policy(model_dir: Path, device: str = "cpu", overrides: dict | None = None):
    config = PreTrainedConfig.from_pretrained(model_dir)
    config.device = device
    for key, value in (overrides or {}).items():
        setattr(config, key, value)
    return get_policy_class(config.type).from_pretrained(model_dir, config=config).eval()


@torch.no_grad()
def stream_cost(model_dir: Path, chunks: int = 5, device: str = "cpu", overrides: dict | None = None) -> dict:
    policy = load_policy(model_dir, device, overrides)
    chunk_len = policy.config.n_action_steps
    obs = {k: torch.zeros(1, *ft.shape, device=device) for k, ft in policy.config.input_features.items()}
    policy.reset()
    for _ in range(chunk_len):  # first chunk: primer, excluded
        policy.select_action(obs)
    with CallProbe(denoisers(policy), torch.device(device)) as probe:
        start = time.perf_counter()
        for _ in range(chunks * chunk_len):
            policy.select_action(obs)
        seconds = time.perf_counter() - start
        calls = probe.calls
    return {"denoiser_calls_per_chunk": calls / chunks, "latency_per_chunk_ms": 1000 * seconds / chunks}
