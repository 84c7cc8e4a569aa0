"""Scripted Lift demonstrations -> LeRobotDataset -> 2 SDP training steps -> 1 evaluation episode.

Everything runs through the installed console commands (lerobot-sdp-record-scripted, lerobot-train,
lerobot-eval) with no extra flags, so it also checks that `--env.type=robomimic` is registered by
the plugin import alone.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip(
    "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
)

BIN = Path(sys.executable).parent
REPO_ID = "local/scripted_lift"


def run(command: list[str], cwd: Path) -> str:
    """Run a console command offline; on failure show its output tail."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_LEROBOT_HOME": str(cwd / "hf_home")}
    done = subprocess.run(command, check=False, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"{command[0]} failed ({done.returncode}):\n{output[-6000:]}"
    return output


def test_plugin_import_registers_the_env():
    """LeRobot's CLIs only import `lerobot_policy_sdp`: that must register --env.type=robomimic."""
    code = (
        "import lerobot_policy_sdp\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "assert 'robomimic' in EnvConfig.get_known_choices(), "
        "'add `from .robomimic import RobomimicEnvConfig` to lerobot_sdp/__init__.py'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_demonstrations_train_and_evaluate(tmp_path):
    data = tmp_path / "lift_demos"
    out = run(
        [
            str(BIN / "lerobot-sdp-record-scripted"),
            "--num_episodes",
            "3",
            "--output_dir",
            str(data),
            "--repo_id",
            REPO_ID,
        ],
        tmp_path,
    )
    assert "kept 3 demonstrations" in out
    info = json.loads((data / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 3 and info["fps"] == 20

    train_dir = tmp_path / "train"
    run(
        [
            str(BIN / "lerobot-train"),
            "--policy.type=sdp",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={data}",
            "--env.type=robomimic",
            "--env.task=Lift",
            "--policy.down_dims=[32,64]",
            "--policy.num_inference_steps=10",
            "--policy.device=cpu",
            "--steps=2",
            "--batch_size=4",
            "--num_workers=0",
            "--env_eval_freq=0",
            "--wandb.enable=false",
            f"--output_dir={train_dir}",
        ],
        tmp_path,
    )
    model = train_dir / "checkpoints" / "last" / "pretrained_model"
    assert (model / "model.safetensors").is_file()

    eval_dir = tmp_path / "eval"
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={model}",
            "--policy.device=cpu",
            "--env.type=robomimic",
            "--env.task=Lift",
            "--env.episode_length=50",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--eval.use_async_envs=false",
            f"--output_dir={eval_dir}",
        ],
        tmp_path,
    )
    metrics = json.loads((eval_dir / "eval_info.json").read_text())["overall"]
    assert metrics["n_episodes"] == 1
    assert 0.0 <= metrics["pc_success"] <= 100.0
    assert list(eval_dir.glob("videos/**/*.mp4")), "lerobot-eval wrote no video"
