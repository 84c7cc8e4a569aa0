"""End to end through LeRobot's real CLIs, as subprocesses: the plugin is found with no extra flags.

Each test builds a tiny local Push-T-shaped LeRobotDataset, trains SDP for a few steps with
`lerobot-train --policy.type=sdp`, and evaluates the checkpoint with `lerobot-eval` on gym-pusht.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from sdp_test_utils import TINY_POLICY_FLAGS, make_tiny_pusht_dataset

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "MUJOCO_GL": "egl"}
TINY_POLICY = [
    *TINY_POLICY_FLAGS,
    "--policy.noise_schemes.chunkwise=0.5",
    "--policy.noise_schemes.independent=0.3",
]


def run(cmd: list[str], timeout: int = 600, env: dict | None = None) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env or ENV)
    assert proc.returncode == 0, f"{' '.join(cmd[:2])} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    return proc.stdout + proc.stderr


def train_args(dataset_root: Path, output_dir: Path, image: bool) -> list[str]:
    args = [
        "--dataset.repo_id=local/tiny_pusht",
        f"--dataset.root={dataset_root}",
        "--steps=2",
        "--batch_size=4",
        "--save_freq=2",
        "--log_freq=1",
        "--num_workers=0",
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
        *TINY_POLICY,
    ]
    if image:
        args += ["--policy.crop_shape=[84,84]", "--policy.spatial_softmax_num_keypoints=4"]
    return args


@pytest.mark.parametrize("image", [False, True], ids=["state", "image"])
def test_train_then_eval_through_the_clis(tmp_path, image):
    root = tmp_path / "dataset"
    make_tiny_pusht_dataset(root, image=image)
    run([str(BIN / "lerobot-train"), *train_args(root, tmp_path / "train", image)])
    model_dir = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    config = json.loads((model_dir / "config.json").read_text())
    assert config["type"] == "sdp" and config["noise_schemes"]["independent"] == 0.3
    obs_type = "pixels_agent_pos" if image else "environment_state_agent_pos"
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={model_dir}",
            "--env.type=pusht",
            f"--env.obs_type={obs_type}",
            "--env.episode_length=12",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--eval.use_async_envs=false",
            "--policy.device=cpu",
            f"--output_dir={tmp_path / 'eval'}",
        ]
    )
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 1
    assert 0.0 <= overall["avg_max_reward"] <= 1.0 and 0.0 <= overall["pc_success"] <= 100.0
    assert "avg_sum_reward" in overall


# The Hub is replaced by a recorder: create_repo answers, upload_folder copies what it would upload.
PUBLISH = """
import shutil, sys, types
from pathlib import Path
from unittest import mock
from huggingface_hub import HfApi, ModelCard

record = Path(sys.argv[1])
uploads = []

def create_repo(self, repo_id, **kwargs):
    return types.SimpleNamespace(repo_id=repo_id)

def upload_folder(self, *, repo_id, folder_path, **kwargs):
    shutil.copytree(folder_path, record / str(len(uploads)))
    uploads.append(repo_id)
    return types.SimpleNamespace(repo_url=types.SimpleNamespace(url="https://hub.invalid/" + repo_id))

with mock.patch.object(HfApi, "create_repo", create_repo), \\
        mock.patch.object(HfApi, "upload_folder", upload_folder), \\
        mock.patch.object(ModelCard, "validate", lambda self, *a, **k: None):
    from lerobot.scripts.lerobot_train import main
    sys.argv = ["lerobot-train", *sys.argv[2:]]
    main()
"""


def test_push_to_hub_uploads_weights_config_processors_and_card(tmp_path):
    root = tmp_path / "dataset"
    make_tiny_pusht_dataset(root)
    record = tmp_path / "uploads"
    args = train_args(root, tmp_path / "train", image=False)
    run(
        [
            sys.executable,
            "-c",
            PUBLISH,
            str(record),
            *args,
            "--policy.push_to_hub=true",
            "--policy.repo_id=someone/sdp_pusht",
        ]
    )
    # record/<upload number>/<repo owner>/<repo name>/<file>
    uploaded = {p.name for p in record.rglob("*") if p.is_file()}
    for expected in [
        "model.safetensors",
        "config.json",
        "train_config.json",
        "README.md",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
    ]:
        assert expected in uploaded, f"{expected} not uploaded; got {sorted(uploaded)}"
    assert any(name.startswith("policy_preprocessor_step_") for name in uploaded)
    card = next(record.rglob("README.md")).read_text()
    assert "Streaming Diffusion Policy (SDP)" in card and "sdp" in card


def test_a_resumed_run_continues_the_noise_curriculum_from_its_step(tmp_path):
    """`lerobot-train --resume=true` rebuilds the policy from the checkpoint: the step the curriculum
    reads (`ema_step`, counted with or without EMA) comes back with it. A 4-step run with a checkpoint
    at step 2 is cut back to that checkpoint and resumed: it ends at step 4, not 2."""
    import shutil

    from safetensors.torch import load_file

    root = tmp_path / "dataset"
    make_tiny_pusht_dataset(root)
    train = tmp_path / "train"
    args = train_args(root, train, image=False)
    args = [a for a in args if not a.startswith(("--steps=", "--save_freq="))]
    curriculum = [
        "--policy.use_ema=false",
        "--policy.noise_curriculum.constant_steps=3",
        "--steps=4",
        "--save_freq=2",
    ]
    run([str(BIN / "lerobot-train"), *args, *curriculum])
    checkpoints = train / "checkpoints"

    def step_of(name):
        return int(load_file(checkpoints / name / "pretrained_model" / "model.safetensors")["ema_step"])

    assert step_of("000002") == 2 and step_of("000004") == 4
    shutil.rmtree(checkpoints / "000004")  # as if the run had stopped after its step-2 checkpoint
    (checkpoints / "last").unlink()
    (checkpoints / "last").symlink_to("000002")
    config = checkpoints / "last" / "pretrained_model" / "train_config.json"
    run([str(BIN / "lerobot-train"), f"--config_path={config}", "--resume=true"])
    assert step_of("000004") == 4
    saved = json.loads((checkpoints / "000004" / "pretrained_model" / "config.json").read_text())
    assert saved["noise_curriculum"] == {"constant_steps": 3, "ramp_steps": 0} and not saved["use_ema"]
