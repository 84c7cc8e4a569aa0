"""The Push-T main job (`lerobot-sdp-pusht`, the README's first command).

1. data: convert the original Diffusion Policy zarr (--zarr, $SDP_PUSHT_ZARR, or ../shared/...) into a
   local keypoints LeRobotDataset; without a zarr, use Hub `lerobot/pusht_keypoints` when online;
2. train SDP with `lerobot-train --config_path=configs/pusht_state_cpu.json`;
3. evaluate with `lerobot-eval` on gym-pusht (batched sync envs);
4. print pc_success, avg_max_reward, the denoiser calls per chunk (counted) and where the videos are.

Stages that already finished are reused with --resume (an interrupted training run resumes from
its last checkpoint); an existing output directory is never overwritten without --overwrite.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_ZARR = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
OBS_TYPE = "environment_state_agent_pos"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output_dir", type=Path, default=Path("outputs/pusht_main"))
    p.add_argument("--config_path", type=Path, default=REPO / "configs" / "pusht_state_cpu.json")
    p.add_argument("--zarr", type=Path, default=None, help="pusht_cchi_v7_replay.zarr (default: $SDP_PUSHT_ZARR, then ../shared/data/pusht/)")
    p.add_argument("--eval_episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=None, help="override the config's training steps")
    p.add_argument("--device", default="cpu")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true", help="reuse finished stages, resume training")
    group.add_argument("--overwrite", action="store_true", help="delete --output_dir and start over")
    return p.parse_args(argv)


def find_zarr(arg: Path | None) -> Path | None:
    if arg is not None:
        if not arg.exists():
            sys.exit(f"error: --zarr {arg} does not exist.")
        return arg
    env = os.environ.get("SDP_PUSHT_ZARR")
    if env:
        if not Path(env).exists():
            sys.exit(f"error: SDP_PUSHT_ZARR={env} does not exist.")
        return Path(env)
    return SHARED_ZARR if SHARED_ZARR.exists() else None


def hub_offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "0").lower() in ("1", "true", "yes", "on")


def dataset_args(args: argparse.Namespace) -> list[str]:
    """lerobot-train's dataset flags: the converted zarr when we have it, else the Hub."""
    zarr = find_zarr(args.zarr)
    if zarr is not None:
        from .pusht_convert import convert_pusht

        root = args.output_dir / "data" / "pusht_keypoints"
        if not (root / "meta" / "info.json").exists():
            print(f"[data] converting {zarr} -> {root}", flush=True)
            convert_pusht(zarr, root, variant="keypoints", repo_id="local/pusht_keypoints", overwrite=True)
        else:
            print(f"[data] reusing {root}", flush=True)
        return ["--dataset.repo_id=local/pusht_keypoints", f"--dataset.root={root}"]
    if hub_offline():
        sys.exit(
            "error: no Push-T data. Pass --zarr /path/to/pusht_cchi_v7_replay.zarr (or set SDP_PUSHT_ZARR), "
            "or go online (unset HF_HUB_OFFLINE) to download lerobot/pusht_keypoints from the Hub."
        )
    print("[data] using lerobot/pusht_keypoints from the Hugging Face Hub", flush=True)
    return ["--dataset.repo_id=lerobot/pusht_keypoints"]


def run_logged(cmd: list[str], log: Path) -> None:
    """Run a LeRobot CLI, echoing its output and keeping a copy in `log`."""
    print(f"[run] {' '.join(cmd)}\n[log] {log}", flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as f, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:
            sys.stdout.write(line)
            f.write(line)
    if proc.returncode != 0:
        sys.exit(f"error: {Path(cmd[0]).name} failed (exit {proc.returncode}); see {log}")


def cli(name: str) -> str:
    return str(Path(sys.executable).parent / name)


def train(args: argparse.Namespace, data: list[str]) -> Path:
    train_dir = args.output_dir / "train"
    last = train_dir / "checkpoints" / "last" / "pretrained_model"
    with args.config_path.open() as f:
        steps = args.steps or json.load(f)["steps"]
    if (last / "train_config.json").exists():
        done = json.loads((last / "train_config.json").read_text())
        if done.get("steps") == steps and (last.parent / "training_state").exists():
            state = json.loads((last.parent / "training_state" / "training_step.json").read_text())
            if state.get("step") == steps:
                print(f"[train] reusing finished run {train_dir}", flush=True)
                return last
        cmd = [cli("lerobot-train"), f"--config_path={last / 'train_config.json'}", "--resume=true"]
    else:
        cmd = [
            cli("lerobot-train"), f"--config_path={args.config_path}", *data, f"--steps={steps}",
            f"--save_freq={steps}", f"--output_dir={train_dir}", f"--policy.device={args.device}",
            "--job_name=sdp_pusht_main",
        ]
    run_logged(cmd, args.output_dir / "logs" / "train.log")
    return last


def evaluate(args: argparse.Namespace, model_dir: Path) -> dict:
    eval_dir = args.output_dir / "eval"
    info_file = eval_dir / "eval_info.json"
    if not info_file.exists():
        n = args.eval_episodes
        run_logged(
            [
                cli("lerobot-eval"), f"--policy.path={model_dir}", "--env.type=pusht", f"--env.obs_type={OBS_TYPE}",
                f"--eval.n_episodes={n}", f"--eval.batch_size={min(n, 50)}", "--eval.use_async_envs=false",
                f"--policy.device={args.device}", f"--output_dir={eval_dir}", "--seed=100000",
            ],
            args.output_dir / "logs" / "eval.log",
        )
    return json.loads(info_file.read_text())["overall"]


def denoiser_calls_per_chunk(model_dir: Path, chunks: int = 3) -> float:
    """Count U-Net calls over a few streaming chunks after the first (the primer is excluded)."""
    from .modeling_sdp import SDPPolicy

    policy = SDPPolicy.from_pretrained(model_dir).to("cpu").eval()
    calls = []
    policy._sampling_model().unet.register_forward_hook(lambda *_: calls.append(1))
    obs = {k: torch.zeros(1, *ft.shape) for k, ft in policy.config.input_features.items()}
    for _ in range(policy.config.n_action_steps):  # first chunk, primer included
        policy.select_action(obs)
    calls.clear()
    for _ in range(chunks * policy.config.n_action_steps):
        policy.select_action(obs)
    return len(calls) / chunks


def prepare_output_dir(args: argparse.Namespace) -> None:
    if args.output_dir.exists() and any(args.output_dir.iterdir()):
        if args.overwrite:
            shutil.rmtree(args.output_dir)
        elif not args.resume:
            sys.exit(
                f"error: {args.output_dir} already exists. Pass --resume to reuse finished stages "
                "(and resume training), --overwrite to delete it, or another --output_dir."
            )
    args.output_dir.mkdir(parents=True, exist_ok=True)


def main(argv=None) -> None:
    args = parse_args(argv)
    if not args.config_path.exists():
        sys.exit(f"error: config {args.config_path} not found; pass --config_path (see the repo's configs/).")
    prepare_output_dir(args)
    t0 = time.monotonic()
    model_dir = train(args, dataset_args(args))
    t_train = time.monotonic() - t0
    metrics = evaluate(args, model_dir)
    calls = denoiser_calls_per_chunk(model_dir)
    config = json.loads((model_dir / "config.json").read_text())
    summary = {
        "pc_success": metrics["pc_success"],
        "avg_max_reward": metrics["avg_max_reward"],
        "avg_sum_reward": metrics["avg_sum_reward"],
        "n_episodes": metrics["n_episodes"],
        "denoiser_calls_per_chunk": calls,
        "num_inference_steps": config["num_inference_steps"] or config["num_train_timesteps"],
        "n_chunks": config["n_chunks"],
        "model_dir": str(model_dir),
        "videos": str(args.output_dir / "eval" / "videos"),
        "wall_time_s": round(time.monotonic() - t0, 1),
        "train_and_data_time_s": round(t_train, 1),
    }
    (args.output_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print("\n=== SDP on Push-T (keypoints) ===")
    print(f"pc_success          {summary['pc_success']:.1f} %  over {summary['n_episodes']} episodes")
    print(f"avg_max_reward      {summary['avg_max_reward']:.3f}")
    print(f"denoiser calls      {calls:g} per chunk (N = {summary['num_inference_steps']}, h = {summary['n_chunks']}; DP: N)")
    print(f"videos              {summary['videos']}")
    print(f"summary             {args.output_dir / 'summary.json'}  ({summary['wall_time_s']:.0f} s in all)")


if __name__ == "__main__":
    main()
