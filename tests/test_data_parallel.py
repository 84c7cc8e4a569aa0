"""Data-parallel training (`data_parallel.py`): every rank draws its own training noise, and
`lerobot-train` under torchrun on two CPU processes (gloo) trains, saves once and averages once."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from sdp_test_utils import TINY_POLICY_FLAGS, make_tiny_pusht_dataset, tiny_config

from lerobot_sdp import SDPPolicy
from lerobot_sdp.data_parallel import rank_generator, world

BIN = Path(sys.executable).parent


def training_batch(cfg, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    batch = {
        k: torch.rand((4, cfg.n_obs_steps, *ft.shape), generator=gen) for k, ft in cfg.input_features.items()
    }
    batch["action"] = torch.rand((4, cfg.geometry.horizon, 2), generator=gen) * 2 - 1
    return batch


# One rank: LeRobot's seeding (the same seed everywhere), the same weights and the same batch, three
# training steps' draws (levels, delays, Gaussian noise) and losses, written to <out>/rank<r>.json.
RANK_DRAWS = """
import json, sys
import torch, torch.distributed as dist
sys.path.insert(0, sys.argv[1])
from sdp_test_utils import tiny_config
from test_data_parallel import training_batch
from lerobot_sdp import SDPPolicy
from lerobot_sdp.noise_schemes import NoiseSchemeWeights
import lerobot_sdp.modeling_sdp as modeling

draws = {"levels": [], "delays": [], "noise": [], "loss": []}
def recorded(name, fn, pick):
    def wrapper(*args, **kwargs):
        out = fn(*args, **kwargs)
        draws[name].append(pick(out).tolist())
        return out
    return wrapper
modeling.sample_levels = recorded("levels", modeling.sample_levels, lambda out: out)
modeling.sample_delays = recorded("delays", modeling.sample_delays, lambda out: out[1])
modeling.gaussian_like = recorded("noise", modeling.gaussian_like, lambda out: out)

dist.init_process_group("gloo")
torch.manual_seed(0)
cfg = tiny_config(max_delay=2, noise_schemes=NoiseSchemeWeights(constant=0.5, chunkwise=0.5))
policy = SDPPolicy(cfg).train()
batch = training_batch(cfg)
draws["loss"] = [float(policy.forward(batch)[0]) for _ in range(3)]
with open(f"{sys.argv[2]}/rank{dist.get_rank()}.json", "w") as f:
    json.dump(draws, f)
dist.destroy_process_group()
"""


def draws_on_two_ranks(tmp_path: Path, run: int) -> dict:
    script = tmp_path / "rank_draws.py"
    script.write_text(RANK_DRAWS)
    out = tmp_path / f"draws{run}"
    out.mkdir()
    # --standalone: a free port, not 29500 for every run (two runs may share the machine under xdist)
    cmd = [
        str(BIN / "torchrun"),
        "--standalone",
        "--nproc_per_node=2",
        str(script),
        str(Path(__file__).parent),
        str(out),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {int(p.stem.removeprefix("rank")): json.loads(p.read_text()) for p in out.glob("rank*.json")}


def test_every_rank_draws_its_own_training_noise_reproducibly(tmp_path):
    first = draws_on_two_ranks(tmp_path, 0)
    assert sorted(first) == [0, 1]
    for name in ("levels", "delays", "noise"):  # the same seed, weights and batch on both ranks
        assert len(first[0][name]) == 3 and first[0][name] != first[1][name], name
    assert first[0]["loss"] != first[1]["loss"]
    # which scheme each sample drew (constant: one level for every slot) differs too
    schemes = {r: [[len(set(sample)) == 1 for sample in step] for step in first[r]["levels"]] for r in (0, 1)}
    assert schemes[0] != schemes[1]
    assert draws_on_two_ranks(tmp_path, 1) == first  # and the same command draws the same noise


def test_one_process_keeps_the_global_stream():
    """Without torch.distributed the loss draws from the global RNG, as before data parallelism."""
    assert world() == (0, 1) and rank_generator(torch.device("cpu")) is None
    cfg = tiny_config(max_delay=1)
    policy = SDPPolicy(cfg).train()
    batch = training_batch(cfg)
    torch.manual_seed(3)
    loss = policy.forward(batch)[0]
    torch.manual_seed(3)
    torch.testing.assert_close(policy.model.compute_loss(batch, None), loss, atol=0, rtol=0)


def checkpoint_weights(train_dir: Path, step: int) -> dict:
    from safetensors.torch import load_file

    return load_file(train_dir / "checkpoints" / f"{step:06d}" / "pretrained_model" / "model.safetensors")


@pytest.mark.slow
def test_two_processes_train_save_once_and_average_once_per_step(tmp_path):
    from diffusers.training_utils import EMAModel

    make_tiny_pusht_dataset(tmp_path / "data")
    steps = 3
    cmd = [
        str(BIN / "torchrun"),
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "lerobot.scripts.lerobot_train",
        "--dataset.repo_id=local/tiny_pusht",
        f"--dataset.root={tmp_path / 'data'}",
        f"--steps={steps}",
        "--batch_size=4",
        "--save_freq=1",
        "--log_freq=1",
        "--num_workers=0",
        "--wandb.enable=false",
        f"--output_dir={tmp_path / 'train'}",
        *TINY_POLICY_FLAGS,
        "--policy.push_to_hub=false",
        # per-position FiLM here; the default flattened step encoder runs in `lerobot-sdp-bench data-parallel`
        "--policy.step_conditioning=film_per_slot",
        # a large step from the first update, so that the weights (and a wrong average) move visibly
        "--policy.optimizer_lr=0.01",
        "--policy.scheduler_warmup_steps=0",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-5000:]  # torchrun exits 0 only when every rank did
    assert "Effective batch size: 4 x 2 = 8" in log
    assert len(re.findall(r"End of training", log)) == 1  # only the main process logs and saves
    train_dir = tmp_path / "train"
    saved = sorted(p.name for p in (train_dir / "checkpoints").iterdir())
    assert saved == [f"{s:06d}" for s in range(1, steps + 1)] + ["last"]

    weights = [checkpoint_weights(train_dir, s) for s in range(1, steps + 1)]
    names = [k.removeprefix("model.") for k in weights[0] if k.startswith("model.")]

    # EMAModel averages parameters that require grad (it copies the others)
    def params(w):
        return [torch.nn.Parameter(w[f"model.{n}"]) for n in names]

    ema = EMAModel(params(weights[0]), use_ema_warmup=True, power=0.75)
    for step, w in enumerate(weights, start=1):
        assert int(w["ema_step"]) == step  # one EMA update per optimizer step, not one per rank
        ema.step(params(w))  # the 1-process replay of the same weights
        for n, shadow in zip(names, ema.shadow_params, strict=True):
            torch.testing.assert_close(w[f"ema_model.{n}"], shadow, rtol=1e-5, atol=1e-6)
    moved = [not torch.equal(weights[0][f"model.{n}"], weights[-1][f"model.{n}"]) for n in names]
    assert sum(moved) > len(names) // 2  # the replay compares weights that really changed

    policy = SDPPolicy.from_pretrained(train_dir / "checkpoints" / "last" / "pretrained_model")
    assert int(policy.ema_step) == steps  # a DDP checkpoint loads (no `module.` prefix) with its EMA
