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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharey="row")
    for name, points in sweeps.items():
        for col, x_key in enumerate(("denoiser_calls_per_chunk", "latency_per_chunk_ms")):
            xs = [p[x_key] for p in points]
            for row, (y_key, se_key) in enumerate(
                (("avg_max_reward", "avg_max_reward_se"), ("pc_success", "pc_success_se"))
            ):
                ax = axes[row, col]
                ax.errorbar(
                    xs,
                    [p[y_key] for p in points],
                    [p.get(se_key, 0.0) for p in points],
                    marker="o",
                    capsize=3,
                    label=name,
                )
                for p, x in zip(points, xs, strict=True):
                    ax.annotate(
                        p["sampler"], (x, p[y_key]), fontsize=7, xytext=(3, 3), textcoords="offset points"
                    )
    for ax in axes.flat:
        ax.set_xscale("log")
        ax.grid(alpha=0.3)
    axes[1, 0].set_xlabel("denoiser calls per chunk")
    axes[1, 1].set_xlabel("latency per chunk, batch 1, CPU (ms)")
    axes[0, 0].set_ylabel("avg_max_reward")
    axes[1, 0].set_ylabel("pc_success (%)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
