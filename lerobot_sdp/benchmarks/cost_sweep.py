"""Quality against cost (`lerobot-sdp-bench quality --sweep`): "why not just run DP with fewer steps?"

The comparison's trained models are evaluated again, without retraining, at several samplers:
Diffusion Policy with DDPM 100 and DDIM 16 / 10 / 8 / 5 / 4 / 2, SDP with DDPM 100 and DDIM 16 / 8 / 4 at
its h (N must stay divisible by h). Every point is a `lerobot-eval` on the run's fixed episodes plus
the counted denoiser calls and the latency of one streamed chunk at batch 1 (`stream_cost`), measured
once every evaluation is done so that none runs beside it; the plot puts avg_max_reward and
pc_success against both, one curve per policy.
"""

from pathlib import Path

from ..chunk_cost import stream_cost
from ..lerobot_cli import Evaluation
from .curves import episode_stats
from .latency_measure import Sampler
from .report import reward_success_plot, save_figure

SAMPLERS = {
    # DDIM 8 and 4: as many calls as SDP h = 2 and h = 4 at DDIM 16
    "diffusion": ("DDPM100", "DDIM16", "DDIM10", "DDIM8", "DDIM5", "DDIM4", "DDIM2"),
    "sdp": ("DDPM100", "DDIM16", "DDIM8", "DDIM4"),
}


def sampler_overrides(text: str) -> dict:
    sampler = Sampler.parse(text)
    return {"noise_scheduler_type": sampler.scheduler, "num_inference_steps": sampler.steps}


def flags(text: str) -> list[str]:
    return [f"--policy.{key}={value}" for key, value in sampler_overrides(text).items()]


def evaluations(policy_type: str, model_dir: Path, here: Path, eval_args: list[str]) -> list[Evaluation]:
    """The `lerobot-eval` runs of one model's sweep, one per sampler of `policy_type`."""
    return [
        Evaluation(
            model_dir, here / "sweep" / text, [*eval_args, *flags(text)], here / "sweep" / f"{text}.log"
        )
        for text in SAMPLERS[policy_type]
    ]


def points(policy_type: str, model_dir: Path, here: Path) -> list[dict]:
    """One point per sampler of `policy_type` once its evaluation is done: episode statistics, denoiser
    calls and latency. Latency is measured here, one chunk after another, so run this alone."""
    return [
        {
            "sampler": text,
            **episode_stats(here / "sweep" / text),
            **stream_cost(model_dir, overrides=sampler_overrides(text)),
        }
        for text in SAMPLERS[policy_type]
    ]


def plot(sweeps: dict[str, list[dict]], path: Path, title: str) -> None:
    """avg_max_reward and pc_success against denoiser calls and latency per chunk, one line per policy,
    each point named by its sampler."""
    x_axes = [
        ("denoiser_calls_per_chunk", "denoiser calls per chunk", 1),
        ("latency_per_chunk_ms", "latency per chunk, batch 1, CPU (ms)", 1),
    ]
    fig, _ = reward_success_plot(sweeps, x_axes, title, annotate="sampler", log_x=True)
    save_figure(fig, path)
