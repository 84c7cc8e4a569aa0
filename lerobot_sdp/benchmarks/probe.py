"""Probe: how much each chunk's denoising relies on the observation, for SDP and LeRobot's DP.

For every policy, on the same dataset windows (every frame of the chosen episodes that starts a
training sample, thinned evenly to at most `--max_windows`), the denoising loss is measured twice on
the same noisy inputs: with each window's own observation conditioning ("true") and with the
conditioning of another window of its batch ("shuffled": the batch's conditionings moved by one, so
no window keeps its own). A network that ignores the observation has the same loss both ways; the
gap is what the observation is worth.

The levels are those each policy's sampler visits: SDP, every one of its s = N/h streaming
staircases (chunk i at k = i*s + o steps remaining, o = 1..s); LeRobot's DP, each of its N levels,
one for all slots. The loss is the epsilon MSE (a sample-predicting network's x0 converted to its
epsilon), per chunk and per band of training timesteps (`--bands` equal bands of 0..T-1). A "chunk"
is the same slot range for both: the past slots and the first n_action_steps actions are chunk 0,
each next n_action_steps slots the next chunk (SDP's trailing padding belongs to its last chunk; DP's
slots past its last full chunk form a shorter one). The noise is drawn from
`--seed` in a fixed order: a rerun gives the same figures.

Held out: the windows are those of the episodes given (`--episodes`, default all of the dataset's);
for figures on data the checkpoints never trained on, pass a recording they did not see (e.g. robomimic
demonstrations recorded from another seed: `lerobot-sdp-record-scripted --seed 200000`).

Results: OUTPUT_DIR/probe.json and OUTPUT_DIR/probe.md.
"""

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..chunk_cost import load_policy
from ..observations import stack_cameras
from ..schedule import PerSlotSchedule
from .policy_args import add_dataset_arguments, add_policy_argument, parse_policies
from .report import table, write_json

PROBED_TYPES = ("sdp", "diffusion")


@dataclass(frozen=True)
class Probe:
    """What every policy is probed on: the windows' frame indices, the bands, the batch, the seed."""

    windows: list[int]
    bands: int = 4
    batch_size: int = 64
    seed: int = 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_policy_argument(p)
    add_dataset_arguments(p)
    p.add_argument(
        "--episodes", type=int, nargs="+", default=None, help="the dataset's episodes to probe (default: all)"
    )
    p.add_argument("--max_windows", type=int, default=512, help="windows, evenly spread over the episodes")
    p.add_argument("--bands", type=int, default=4, help="equal bands of the training timesteps")
    p.add_argument("--batch_size", type=int, default=64, help="windows per batch (the shuffle's pool)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise")
    p.add_argument("--device", default="cpu")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/probe"))


def window_indices(episode_ranges: list[tuple[int, int]], max_windows: int) -> list[int]:
    """Every frame of the episodes (each starts a training window), thinned evenly to `max_windows`."""
    frames = [i for start, end in episode_ranges for i in range(start, end)]
    if not frames:
        raise SystemExit("No frames to probe: the episodes chosen are empty.")
    if len(frames) <= max_windows:
        return frames
    return [frames[round(j * (len(frames) - 1) / (max_windows - 1))] for j in range(max_windows)]


def slot_chunks(horizon: int, n_past: int, chunk_len: int) -> Tensor:
    """(horizon,) chunk of every slot of a DP horizon: the past slots and the first chunk_len after
    them 0, then one chunk per chunk_len slots (the last may be shorter)."""
    j = torch.arange(horizon)
    return (j - n_past).clamp(min=0) // chunk_len


def network(policy):
    """The network the policy samples with in eval mode: SDP's EMA copy when it keeps one (the raw
    weights otherwise), DP's diffusion model."""
    return policy._sampling_model() if policy.config.type == "sdp" else policy.diffusion


def level_patterns(policy) -> tuple[Tensor, Tensor, PerSlotSchedule]:
    """(P, horizon) training timesteps of every level pattern the policy's sampler visits, each slot's
    chunk (horizon,), and the per-slot schedule."""
    cfg = policy.config
    if cfg.type == "sdp":
        model = policy.model
        g = model.geometry
        k = g.slot_chunk.unsqueeze(0) * g.steps_per_call + torch.arange(1, g.steps_per_call + 1).unsqueeze(1)
        k = k.to(model.schedule.timestep_table.device)
        return model.schedule.train_timesteps(k), g.slot_chunk, model.schedule
    model = policy.diffusion
    schedule = PerSlotSchedule(model.noise_scheduler, model.num_inference_steps)
    schedule.to(next(model.parameters()).device)
    k = torch.arange(1, model.num_inference_steps + 1).unsqueeze(1).expand(-1, cfg.horizon)
    chunks = slot_chunks(cfg.horizon, cfg.n_obs_steps - 1, cfg.n_action_steps)
    return schedule.train_timesteps(k.to(schedule.timestep_table.device)), chunks, schedule


def epsilon_error(policy, schedule, x_t, t, global_cond, eps) -> Tensor:
    """(B, T, A) squared error of the network's epsilon at per-slot timesteps ``t`` (B, T)."""
    steps = t if policy.config.type == "sdp" else t[:, 0]  # DP takes one timestep per sample
    out = network(policy).unet(x_t, steps, global_cond=global_cond)
    if policy.config.prediction_type == "sample":
        abar = schedule.alpha_bar(t)
        out = (x_t - abar.sqrt() * out) / (1 - abar).sqrt()
    return (out.float() - eps).pow(2)


@torch.no_grad()
def probe_policy(policy, preprocessor, dataset, probe: Probe) -> dict:
    """{"true", "shuffled", "count"}: (chunks, bands) sums of squared epsilon error over the windows,
    and how many values each sum holds."""
    if policy.config.type not in PROBED_TYPES:
        raise SystemExit(f"The probe takes {' or '.join(PROBED_TYPES)} policies, got {policy.config.type!r}.")
    policy.eval()
    patterns, chunks, schedule = level_patterns(policy)
    device = patterns.device
    chunks = chunks.to(device)
    n_chunks = int(chunks.max()) + 1
    bands = (patterns * probe.bands) // schedule.num_train_timesteps  # (P, T)
    cell = chunks.unsqueeze(0) * probe.bands + bands  # (P, T): the (chunk, band) of every slot
    sums = {"true": torch.zeros(n_chunks * probe.bands, device=device)}
    sums["shuffled"] = torch.zeros_like(sums["true"])
    count = torch.zeros_like(sums["true"])
    generator = torch.Generator(device).manual_seed(probe.seed)
    model = network(policy)
    for start in range(0, len(probe.windows), probe.batch_size):
        frames = [dataset[i] for i in probe.windows[start : start + probe.batch_size]]
        batch = preprocessor(torch.utils.data.default_collate(frames))
        batch = stack_cameras(policy.config, batch)
        conds = {"true": model._prepare_global_conditioning(batch)}
        conds["shuffled"] = conds["true"].roll(1, dims=0)
        actions = batch["action"].float()
        size = actions.shape[0]
        for p in range(patterns.shape[0]):
            t = patterns[p].expand(size, -1)
            eps = torch.randn(actions.shape, generator=generator, device=device)
            x_t = schedule.add_noise(actions, eps, t)
            count.index_add_(
                0, cell[p], torch.full_like(cell[p], size * actions.shape[-1], dtype=count.dtype)
            )
            for name, cond in conds.items():
                err = epsilon_error(policy, schedule, x_t, t, cond, eps).sum(-1)  # (B, T)
                sums[name].index_add_(0, cell[p], err.sum(0))
    shape = (n_chunks, probe.bands)
    return {k: v.view(shape).cpu() for k, v in sums.items()} | {"count": count.view(shape).cpu()}


def rows_of(name: str, sums: dict, num_train_timesteps: int, bands: int) -> list[dict]:
    """One row per (chunk, band) that the policy's levels reach, then each chunk over all bands."""
    rows = []
    n_chunks = sums["count"].shape[0]
    for chunk in range(n_chunks):
        cells = [b for b in range(bands) if sums["count"][chunk, b] > 0]
        for b in [*cells, None]:
            sel = slice(None) if b is None else slice(b, b + 1)
            n = float(sums["count"][chunk, sel].sum())
            true = float(sums["true"][chunk, sel].sum()) / n
            shuffled = float(sums["shuffled"][chunk, sel].sum()) / n
            lo, hi = (0, num_train_timesteps) if b is None else band_edges(b, bands, num_train_timesteps)
            rows.append(
                {
                    "policy": name,
                    "chunk": chunk,
                    "band": "all" if b is None else f"{lo}-{hi - 1}",
                    "loss_true": true,
                    "loss_shuffled": shuffled,
                    "shuffled_over_true": shuffled / true if true > 0 else math.inf,
                    "n_values": int(n),
                }
            )
    return rows


def band_edges(b: int, bands: int, num_train_timesteps: int) -> tuple[int, int]:
    """[lo, hi) of band b: the timesteps t with t * bands // T == b."""
    return math.ceil(b * num_train_timesteps / bands), math.ceil((b + 1) * num_train_timesteps / bands)


def markdown(report: dict) -> str:
    header = [
        "policy",
        "chunk",
        "timesteps",
        "loss, true obs.",
        "loss, shuffled obs.",
        "shuffled / true",
        "values",
    ]
    rows = [
        [
            r["policy"],
            r["chunk"],
            r["band"],
            f"{r['loss_true']:.4f}",
            f"{r['loss_shuffled']:.4f}",
            f"{r['shuffled_over_true']:.2f}",
            r["n_values"],
        ]
        for r in report["rows"]
    ]
    s = report["settings"]
    intro = (
        f"Epsilon MSE on {s['n_windows']} windows of {s['dataset_root']} (episodes {s['episodes']}), "
        f"noise seed {s['seed']}, batches of {s['batch_size']}: each policy at the levels its sampler visits."
    )
    return "\n".join([intro, "", *table(header, rows)]) + "\n"


def open_dataset(root: Path, repo_id: str, config):
    """The dataset at ``root``, its windows laid out for ``config`` (observation history, horizon)."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata(repo_id, root=root)
    return LeRobotDataset(repo_id, root=root, delta_timestamps=resolve_delta_timestamps(config, meta))


def episode_ranges(dataset, episodes: list[int] | None) -> tuple[list[int], list[tuple[int, int]]]:
    """The chosen episodes (all by default) and their [first, last + 1) frame indices."""
    meta = dataset.meta.episodes
    chosen = list(range(len(meta))) if episodes is None else episodes
    unknown = [e for e in chosen if not 0 <= e < len(meta)]
    if unknown:
        raise SystemExit(f"--episodes {unknown}: the dataset has episodes 0..{len(meta) - 1}.")
    ranges = [(int(meta[e]["dataset_from_index"]), int(meta[e]["dataset_to_index"])) for e in chosen]
    return chosen, ranges


def probe_models(
    policies: dict[str, Path],
    dataset_root: Path,
    repo_id: str,
    episodes: list[int] | None = None,
    probe: Probe | None = None,
    max_windows: int = 512,
    device: str = "cpu",
) -> dict:
    """The report of every policy (name -> pretrained_model folder) on the episodes' windows, with
    ``probe``'s bands, batch and seed (its windows are chosen here)."""
    from lerobot.policies.factory import make_pre_post_processors

    settings = probe or Probe([])
    if settings.bands < 1 or settings.batch_size < 2 or max_windows < 2:
        raise SystemExit(
            "--bands must be at least 1, --batch_size at least 2 (the shuffle swaps conditionings within "
            "a batch) and --max_windows at least 2."
        )
    report = {"policies": {}, "rows": []}
    for name, path in policies.items():
        policy = load_policy(path, device)
        dataset = open_dataset(dataset_root, repo_id, policy.config)
        chosen, ranges = episode_ranges(dataset, episodes)
        this = Probe(window_indices(ranges, max_windows), settings.bands, settings.batch_size, settings.seed)
        preprocessor, _ = make_pre_post_processors(
            policy_cfg=policy.config, pretrained_path=str(path), preprocessor_overrides={}
        )
        sums = probe_policy(policy, preprocessor, dataset, this)
        report["rows"] += rows_of(name, sums, policy.config.num_train_timesteps, this.bands)
        report["policies"][name] = {"path": str(path), "type": policy.config.type}
        report["settings"] = {
            "dataset_root": str(dataset_root),
            "episodes": "all" if episodes is None else chosen,
            "n_windows": len(this.windows),
            "bands": this.bands,
            "batch_size": this.batch_size,
            "seed": this.seed,
        }
    return report


def run(args: argparse.Namespace) -> dict:
    probe = Probe([], args.bands, args.batch_size, args.seed)
    report = probe_models(
        parse_policies(args.policy),
        args.dataset_root,
        args.repo_id,
        args.episodes,
        probe,
        args.max_windows,
        args.device,
    )
    args.output_dir.mkdir(parents=True, exist_ok=True)
    write_json(args.output_dir / "probe.json", report)
    text = markdown(report)
    (args.output_dir / "probe.md").write_text(text)
    print(text)
    return report
