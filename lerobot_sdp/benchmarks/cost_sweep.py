"""Quality against cost (`lerobot-sdp-bench quality --sweep`): "why not just run DP with fewer steps?"

The comparison's trained models are evaluated again, without retraining, at several samplers:
Diffusion Policy with DDPM 100 and DDIM 16 / 10 / 5 / 2, SDP with DDPM 100 and DDIM 16 / 8 / 4 at
its h (N must stay divisible by h). Every point is a `lerobot-eval` on the run's fixed episodes plus
the counted denoiser calls and the latency of one streamed chunk at batch 1 (`stream_cost`); the
plot puts avg_max_reward and pc_success against both, one curve per policy.
"""

from pathlib import Path

from ..chunk_cost import stream_cost
from ..lerobot_cli import evaluate
from .curves import episode_stats
from .latency_measure import Sampler
from .report import reward_success_plot, save_figure

SAMPLERS = {
    "diffusion": ("DDPM100", "DDIM16", "DDIM10", "DDIM5", "DDIM2"),
    "sdp": ("DDPM100", "DDIM16", "DDIM8", "DDIM4"),
}


def sampler_overrides(text: str) -> dict:
    sampler = Sampler.parse(text)
    return {"noise_scheduler_type": sampler.scheduler, "num_inference_steps": sampler.steps}


def sweep(policy_type: str, model_dir: Path, here: Path, eval_args: list[str]) -> list[dict]:
    """One point per sampler of `policy_type`: episode statistics, denoiser calls, latency."""
    points = []
    for text in SAMPLERS[policy_type]:
        overrides = sampler_overrides(text)
        flags = [f"--policy.{key}={value}" for key, value in overrides.items()]
        eval_dir = here / "sweep" / text
        evaluate(model_dir, eval_dir, [*eval_args, *flags], here / "sweep" / f"{text}.log")
        points.append(
            {"sampler": text, **episode_stats(eval_dir), **stream_cost(model_dir, overrides=overrides)}
        )
    return points


def plot(sweeps: dict[str, list[dict]], path: Path, title: str) -> None:
    """avg_max_reward and pc_success against denoiser calls and latency per chunk, one line per policy,
    each point named by its sampler."""
    x_axes = [
        ("denoiser_calls_per_chunk", "denoiser calls per chunk", 1),
        ("latency_per_chunk_ms", "latency per chunk, batch 1, CPU (ms)", 1),
    ]
    fig, _ = reward_success_plot(sweeps, x_axes, title, annotate="sampler", log_x=True)
    save_figure(fig, path)
