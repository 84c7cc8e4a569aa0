"""`lerobot-sdp-bench train-profile` on a tiny dataset: every policy of every config built as
`lerobot-train` builds it and stepped in turn (the order reversed every other round), one row each
with its phases and its model time against the first row's (plumbing, not timed)."""

import json

from sdp_test_utils import make_tiny_pusht_dataset

from lerobot_sdp import shipped_configs
from lerobot_sdp.benchmarks import cli, train_profile


def tiny_config(path, **policy):
    raw = json.loads(shipped_configs.path("pusht_state_cpu").read_text())
    raw["policy"].update(down_dims=[16, 32], diffusion_step_embed_dim=16, **policy)
    raw.update(batch_size=4, num_workers=0)
    path.write_text(json.dumps(raw))
    return path


def test_configs_and_policies_take_their_steps_in_turn(tmp_path, monkeypatch, capsys):
    make_tiny_pusht_dataset(tmp_path / "data", n_episodes=2, length=40)
    md0 = tiny_config(tmp_path / "md0.json")
    md3 = tiny_config(tmp_path / "md3.json", max_delay=3)
    order, real_step = [], train_profile.take_step
    monkeypatch.setattr(train_profile, "take_step", lambda c: (order.append(c.name), real_step(c)))
    out = tmp_path / "out"
    cli.main(["train-profile", "--config_path", str(md0), str(md3), "--policies", "sdp", "diffusion",
              "--dataset_root", str(tmp_path / "data"), "--repo_id", "local/tiny_pusht",
              "--steps", "2", "--warmup", "1", "--output_dir", str(out)])  # fmt: skip
    names = ["sdp (md0)", "diffusion (md0)", "sdp (md3)", "diffusion (md3)"]
    assert order == names + names[::-1] + names  # warm-up round, then two timed rounds
    rows = json.loads((out / "train_profile.json").read_text())["rows"]
    assert [r["name"] for r in rows] == names
    assert [r["policy"] for r in rows] == ["sdp", "diffusion"] * 2
    # the U-Net downsamples once here (multiples of 2); max_delay 3 makes room for 3 committed slots
    assert [r["horizon"] for r in rows] == [34, 34, 36, 36]
    assert rows[0]["model_time_vs_first"] == 1.0
    for r in rows:
        assert all(ms >= 0 for ms in r["phase_ms"].values()) and r["phase_ms"]["forward"] > 0
        assert r["step_ms"] == sum(r["phase_ms"].values())
    assert "| sdp (md3) | 36 |" in capsys.readouterr().out


def test_bf16_rows_run_the_forward_under_autocast(tmp_path, monkeypatch):
    import torch

    make_tiny_pusht_dataset(tmp_path / "data", n_episodes=2, length=40)
    seen, real_build = [], train_profile.build

    def recording_build(*args, **kwargs):
        c = real_build(*args, **kwargs)
        forward = c.forward
        c.forward = lambda batch: (
            seen.append((c.name, torch.is_autocast_enabled("cpu"))),
            forward(batch),
        )[1]
        return c

    monkeypatch.setattr(train_profile, "build", recording_build)
    out = tmp_path / "out"
    cli.main(["train-profile", "--config_path", str(tiny_config(tmp_path / "c.json")), "--policies", "sdp",
              "--precision", "fp32", "bf16", "--dataset_root", str(tmp_path / "data"),
              "--repo_id", "local/tiny_pusht", "--steps", "1", "--warmup", "0",
              "--output_dir", str(out)])  # fmt: skip
    assert sorted(set(seen)) == [("sdp bf16", True), ("sdp fp32", False)]
    rows = json.loads((out / "train_profile.json").read_text())["rows"]
    assert [(r["name"], r["precision"]) for r in rows] == [("sdp fp32", "fp32"), ("sdp bf16", "bf16")]


def test_threads_and_data_paths_are_set_per_contender_from_the_same_weights(tmp_path, monkeypatch):
    import torch

    from lerobot_sdp import memory_dataset

    make_tiny_pusht_dataset(tmp_path / "data", n_episodes=2, length=40)
    seen, built, real_build = [], [], train_profile.build

    def recording_build(*args, **kwargs):
        c = real_build(*args, **kwargs)
        forward = c.forward
        c.forward = lambda batch: (seen.append((c.name, torch.get_num_threads())), forward(batch))[1]
        built.append((c, {n: p.detach().clone() for n, p in c.policy.named_parameters()}))
        return c

    monkeypatch.setattr(train_profile, "build", recording_build)
    out = tmp_path / "out"
    cli.main(["train-profile", "--config_path", str(tiny_config(tmp_path / "c.json")), "--policies", "sdp",
              "--num_threads", "1", "2", "--data", "memory", "lerobot",
              "--dataset_root", str(tmp_path / "data"), "--repo_id", "local/tiny_pusht",
              "--steps", "4", "--warmup", "1", "--loss_bin", "2",
              "--output_dir", str(out)])  # fmt: skip
    names = ["sdp 1t memory", "sdp 1t lerobot", "sdp 2t memory", "sdp 2t lerobot"]
    assert sorted(set(seen)) == sorted((n, int(n.split()[1][0])) for n in names)
    for c, start in built:
        reader = c.dataset._ensure_reader()
        assert (memory_dataset.table_of(reader) is None) == (c.variant.data == "lerobot"), c.name
        assert all(torch.equal(w, built[0][1][n]) for n, w in start.items()), "not the same initial weights"
    report = json.loads((out / "train_profile.json").read_text())
    rows = report["rows"]
    assert [r["name"] for r in rows] == names
    assert all(len(r["losses"]) == 4 for r in rows)
    assert [a["name"] for a in report["loss_agreement"]] == names
    assert all(len(a["bins"]) == 2 for a in report["loss_agreement"])
    assert (out / "loss_curves.png").stat().st_size > 0


def test_the_loss_comparison_bins_and_scores_by_hand():
    rows = [{"name": "a", "losses": [1.0, 3.0, 2.0, 2.0]}, {"name": "b", "losses": [2.0, 4.0, 2.0, 2.0]}]
    bins_a = train_profile.loss_bins(rows[0]["losses"], 2)
    # bin 1: mean 2, std sqrt(2), SE sqrt(2)/sqrt(2) = 1; bin 2: mean 2, SE 0
    assert bins_a == [(2.0, 1.0), (2.0, 0.0)]
    agreement = train_profile.loss_agreement(rows, 2)
    # b's bin 1: mean 3, SE 1 -> |3 - 2| / hypot(1, 1) = 0.7071; bin 2: equal means, no spread -> 0
    b = agreement[1]
    assert abs(b["bins"][0][0] - 3.0) < 1e-12
    assert abs(b["max_abs_z"] - 2**-0.5) < 1e-9
    assert train_profile.z_score(0.5, 0.0) == float("inf") and train_profile.z_score(0.0, 0.0) == 0.0


def test_the_limit_rows_divide_the_counted_flops_by_the_probed_rate(tmp_path):
    make_tiny_pusht_dataset(tmp_path / "data", n_episodes=2, length=40)
    out = tmp_path / "out"
    cli.main(["train-profile", "--config_path", str(tiny_config(tmp_path / "c.json")), "--policies", "sdp",
              "--num_threads", "1", "--limit", "--dataset_root", str(tmp_path / "data"),
              "--repo_id", "local/tiny_pusht", "--steps", "2", "--warmup", "1",
              "--output_dir", str(out)])  # fmt: skip
    (row,) = json.loads((out / "train_profile.json").read_text())["rows"]
    assert row["gflop_per_step"] > 0 and row["peak_gflops"] == max(row["gemm_gflops"], row["conv1d_gflops"])
    assert abs(row["limit_ms"] - row["gflop_per_step"] / row["peak_gflops"] * 1e3) < 1e-9
    assert abs(row["model_over_limit"] - row["model_ms"] / row["limit_ms"]) < 1e-9
