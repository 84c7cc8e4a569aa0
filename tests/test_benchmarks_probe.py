"""`lerobot-sdp-bench probe`: the denoising loss with the true and with shuffled observations."""

import json

import numpy as np
import pytest
import torch
from sdp_test_utils import tiny_config, tiny_dp_config

from lerobot_sdp.benchmarks import cli
from lerobot_sdp.benchmarks.probe import (
    Probe,
    network,
    open_dataset,
    probe_policy,
    slot_chunks,
    window_indices,
)

REPO_ID = "local/probe"


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    """4 episodes of 12 frames, each holding one random pose: state = action for all its frames, so
    a window's (normalised) actions are its observation's state repeated."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path_factory.mktemp("probe") / "data"
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "observation.environment_state": {"dtype": "float32", "shape": (16,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
    }
    ds = LeRobotDataset.create(REPO_ID, fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for _ in range(4):
        pose = rng.uniform(0, 512, 2).astype(np.float32)
        for _ in range(12):
            env = rng.uniform(0, 512, 16).astype(np.float32)
            ds.add_frame(
                {
                    "observation.state": pose,
                    "action": pose,
                    "observation.environment_state": env,
                    "task": "hold",
                }
            )
        ds.save_episode()
    ds.finalize()
    return root


def configs():
    sdp, dp = tiny_config(), tiny_dp_config(num_inference_steps=10)
    return {"sdp": sdp, "diffusion": dp}


def built(kind, root):
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = configs()[kind]
    dataset = open_dataset(root, REPO_ID, cfg)
    torch.manual_seed(0)
    policy = get_policy_class(kind)(cfg)
    preprocessor, _ = make_pre_post_processors(cfg, dataset_stats=dataset.meta.stats)
    return policy, preprocessor, dataset


def unet_of(policy):
    """The U-Net the probe reads: the one the policy samples with in eval mode."""
    return network(policy.eval()).unet


def oracle(policy):
    """A denoiser that reads the clean actions off the conditioning (the state, the first two values)
    and returns its target for them: the exact epsilon of its input, or the clean actions."""
    model = policy.model if policy.config.type == "sdp" else policy.diffusion
    abar_of = model.noise_scheduler.alphas_cumprod.float()

    def forward(x, t, global_cond=None):
        x0 = global_cond[:, None, :2].expand_as(x)
        if policy.config.prediction_type == "sample":
            return x0
        t = t if t.ndim == 2 else t.unsqueeze(1).expand(-1, x.shape[1])
        abar = abar_of[t].unsqueeze(-1)
        return (x - abar.sqrt() * x0) / (1 - abar).sqrt()

    return forward


@pytest.mark.parametrize("kind", ["sdp", "diffusion"])
def test_a_network_that_ignores_the_observation_loses_nothing_when_it_is_shuffled(dataset_root, kind):
    policy, preprocessor, dataset = built(kind, dataset_root)
    unet = unet_of(policy)
    forward = unet.forward
    unet.forward = lambda x, t, global_cond=None: forward(x, t, global_cond=torch.zeros_like(global_cond))
    sums = probe_policy(policy, preprocessor, dataset, Probe(list(range(48)), bands=4, batch_size=16))
    assert torch.equal(sums["true"], sums["shuffled"])
    assert (sums["true"].sum(1) > 0).all()  # every chunk measured
    # DDPM 10 over 100 timesteps: t = 0, 10, ..., 90; 4 bands of 25
    if kind == "diffusion":  # every level on every slot: 10 levels x 48 windows x 2 dims per slot
        per_band = torch.tensor([3, 2, 3, 2]) * 48 * 2
        assert torch.equal(sums["count"], torch.stack([per_band * 5, per_band * 3]).float())  # 5 + 3 slots


@pytest.mark.parametrize(
    "kind, prediction_type", [("sdp", "epsilon"), ("diffusion", "epsilon"), ("sdp", "sample")]
)
def test_a_network_that_reads_the_actions_off_the_observation_shows_the_gap_in_every_chunk(
    dataset_root, kind, prediction_type
):
    policy, preprocessor, dataset = built(kind, dataset_root)
    policy.config.prediction_type = prediction_type  # scored on its epsilon all the same
    unet_of(policy).forward = oracle(policy)
    sums = probe_policy(policy, preprocessor, dataset, Probe(list(range(48)), bands=4, batch_size=16))
    measured = sums["count"] > 0
    true = sums["true"][measured] / sums["count"][measured]
    shuffled = sums["shuffled"][measured] / sums["count"][measured]
    assert (true < 1e-6).all()
    assert (shuffled > 1e-3).all()
    # the observation matters most where the noise is least: chunk 0's lowest band
    low = sums["shuffled"][0, 0] / sums["count"][0, 0]
    assert float(low) == pytest.approx(float(shuffled.max()))


def test_an_sdp_policy_with_ema_is_probed_on_the_averaged_weights_it_samples_with(dataset_root):
    policy, preprocessor, dataset = built("sdp", dataset_root)
    assert policy.config.use_ema  # SDPConfig's default
    policy.ema_model.unet.forward = oracle(policy)  # the raw weights stay an untrained network
    sums = probe_policy(policy, preprocessor, dataset, Probe(list(range(48)), bands=4, batch_size=16))
    measured = sums["count"] > 0
    assert (sums["true"][measured] / sums["count"][measured] < 1e-6).all()


def test_windows_and_chunks():
    assert window_indices([(0, 3), (10, 12)], 10) == [0, 1, 2, 10, 11]
    assert window_indices([(0, 100)], 3) == [0, 50, 99]
    # DP's horizon 16, To 2, Tb 8: the past slot and 8 actions, then the last 7 slots
    assert slot_chunks(16, 1, 8).tolist() == [0] * 9 + [1] * 7
    assert slot_chunks(8, 1, 4).tolist() == [0] * 5 + [1] * 3


def test_the_command_writes_one_table_for_sdp_and_dp_and_repeats_it(dataset_root, tmp_path):
    from lerobot.policies.factory import make_pre_post_processors

    specs = []
    for kind, cfg in configs().items():
        policy, _, dataset = built(kind, dataset_root)
        path = tmp_path / kind
        policy.save_pretrained(path)
        for pipeline in make_pre_post_processors(cfg, dataset_stats=dataset.meta.stats):
            pipeline.save_pretrained(path)
        specs += ["--policy", f"{kind}={path}"]
    reports = []
    for out in ("a", "b"):
        args = ["probe", *specs, "--dataset_root", str(dataset_root), "--repo_id", REPO_ID]
        cli.main(
            [
                *args,
                "--episodes",
                "1",
                "3",
                "--max_windows",
                "20",
                "--batch_size",
                "8",
                "--output_dir",
                str(tmp_path / out),
            ]
        )
        reports.append(json.loads((tmp_path / out / "probe.json").read_text()))
    assert reports[0] == reports[1]  # seeded noise, the same windows
    rows = reports[0]["rows"]
    assert {r["policy"] for r in rows} == {"sdp", "diffusion"}
    assert reports[0]["settings"]["n_windows"] == 20 and reports[0]["settings"]["episodes"] == [1, 3]
    sdp = {(r["chunk"], r["band"]): r for r in rows if r["policy"] == "sdp"}
    # SDP h = 2 at DDPM 10: chunk 0 at t = 0..40, chunk 1 at t = 50..90
    assert set(sdp) == {(0, "0-24"), (0, "25-49"), (0, "all"), (1, "50-74"), (1, "75-99"), (1, "all")}
    text = (tmp_path / "a" / "probe.md").read_text()
    assert "| policy | chunk | timesteps | loss, true obs. | loss, shuffled obs." in text
    with pytest.raises(SystemExit, match=r"episodes 0\.\.3"):
        cli.main([*args, "--episodes", "7", "--output_dir", str(tmp_path / "c")])
