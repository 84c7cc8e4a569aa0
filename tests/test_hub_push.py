"""Publishing to the Hub: `lerobot-train ... --policy.push_to_hub=true --policy.repo_id=...` runs LeRobot's
own push path (`PreTrainedPolicy.push_model_to_hub`, then the pre/post-processors' `push_to_hub`) at
the end of training. Here huggingface_hub's repo creation and folder upload are intercepted: no network,
and the folder that would be uploaded is kept, then loaded back as a user loads a Hub policy."""

import fnmatch
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from huggingface_hub import HfApi, RepoCard
from sdp_test_utils import TINY_POLICY_FLAGS, make_tiny_pusht_dataset

from lerobot_sdp import SDPPolicy

REPO_ID = "someone/sdp_tiny_pusht"


def _intercept_uploads(monkeypatch, into: Path) -> list[dict]:
    """Replace HfApi.create_repo / upload_folder: every uploaded file lands in ``into`` (as the repo
    would hold it, allow/ignore patterns applied); returns the log of upload calls. The model card's
    validation (a request to the Hub's YAML validator) is skipped, and logged."""
    uploads = []

    def create_repo(self, repo_id, **kwargs):
        return SimpleNamespace(repo_id=repo_id, url=f"https://huggingface.co/{repo_id}")

    def upload_folder(self, *, repo_id, folder_path, allow_patterns=None, ignore_patterns=None, **kwargs):
        def wanted(name: str) -> bool:
            allowed = allow_patterns is None or any(fnmatch.fnmatch(name, p) for p in allow_patterns)
            return allowed and not any(fnmatch.fnmatch(name, p) for p in ignore_patterns or [])

        sent = sorted(p.name for p in Path(folder_path).iterdir() if p.is_file() and wanted(p.name))
        for name in sent:
            shutil.copy2(Path(folder_path) / name, into / name)
        uploads.append({"repo_id": repo_id, "files": sent})
        return SimpleNamespace(repo_url=SimpleNamespace(url=f"https://huggingface.co/{repo_id}"))

    into.mkdir()
    monkeypatch.setattr(RepoCard, "validate", lambda self, *a, **k: uploads.append({"validated": True}))
    monkeypatch.setattr(HfApi, "create_repo", create_repo)
    monkeypatch.setattr(HfApi, "upload_folder", upload_folder)
    return uploads


@pytest.mark.slow
def test_lerobot_train_pushes_a_policy_that_loads_back_and_acts(tmp_path, monkeypatch):
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.scripts import lerobot_train

    root = tmp_path / "dataset"
    make_tiny_pusht_dataset(root)
    hub = tmp_path / "hub_repo"
    uploads = _intercept_uploads(monkeypatch, hub)
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "lerobot-train",
            "--dataset.repo_id=local/tiny_pusht",
            f"--dataset.root={root}",
            "--steps=2",
            "--batch_size=4",
            "--save_freq=2",
            "--num_workers=0",
            "--wandb.enable=false",
            f"--output_dir={tmp_path / 'train'}",
            *TINY_POLICY_FLAGS,
            "--policy.push_to_hub=true",
            f"--policy.repo_id={REPO_ID}",
        ],
    )
    lerobot_train.main()

    # one upload for the policy, one per processor pipeline, all to the named repository
    assert [u.get("repo_id") for u in uploads if "files" in u] == [REPO_ID] * 3
    files = {p.name for p in hub.iterdir()}
    assert {"README.md", "config.json", "model.safetensors", "train_config.json"} <= files
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= files
    # the normaliser statistics travel with the processors, as safetensors
    assert any(f.startswith("policy_preprocessor_step_") and f.endswith(".safetensors") for f in files)
    card = (hub / "README.md").read_text()
    assert "Streaming Diffusion Policy (SDP)" in card and "local/tiny_pusht" in card  # intro, dataset

    # loaded back from the folder a user would download, then run on an unnormalised observation
    policy = SDPPolicy.from_pretrained(hub).eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(hub))
    trained = SDPPolicy.from_pretrained(tmp_path / "train" / "checkpoints" / "last" / "pretrained_model")
    for key, value in trained.state_dict().items():
        assert torch.equal(policy.state_dict()[key], value), key
    obs = {
        "observation.state": torch.tensor([[200.0, 300.0]]),
        "observation.environment_state": torch.rand(1, 16) * 512,
        "task": ["Push the T-shaped block onto the T-shaped target."],
    }
    action = post(policy.select_action(pre(obs)))
    assert action.shape == (1, 2) and torch.isfinite(action).all()
