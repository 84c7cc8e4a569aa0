"""What one streamed action chunk of a trained policy costs: denoiser calls (counted with forward
hooks) and wall time, measured through `select_action` on the CPU after the first chunk (primer)."""

import time
from pathlib import Path

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class

from .latency_measure import CallProbe, denoisers


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
