"""The data-parallel benchmark: reading LeRobot's loss logs, the verdict, and a tiny run through
`lerobot-train` (one and two processes) and `lerobot-eval`."""

import json

import pytest
from sdp_test_utils import make_tiny_pusht_dataset

from lerobot_sdp import shipped_configs
from lerobot_sdp.benchmarks import cli
from lerobot_sdp.benchmarks.curves import loss_logs
from lerobot_sdp.benchmarks.data_parallel import curve_distance, verdict

LOG = """\
Training:   6%|6         | 50/800 [00:20<05:00,  2.50step/s]INFO 2026-12-02 12:25:22 ot_train.py:641 \
step:250 smpl:16K ep:10 epch:0.6 loss:0.412 grdn:3.1 lr:2.0e-04 updt_s:0.15 data_s:0.09 smp/s:182
INFO 2026-12-02 12:25:23 ot_train.py:687 Checkpoint policy after step 250
INFO 2026-12-02 12:25:42 ot_train.py:641 step:1K smpl:64K ep:10 epch:2.5 loss:0.05 grdn:1.0 lr:1.0e-04 \
updt_s:0.15 data_s:0.09 smp/s:1.2K
"""


def test_loss_logs_read_the_exact_step_loss_and_rate(tmp_path):
    log = tmp_path / "train.log"
    log.write_text(LOG)
    # the progress bar gives the exact step of a resumed run (250 = 1000 - 800 + 50); without one,
    # LeRobot's rounded step
    assert loss_logs(log, final_step=1000) == [
        {"step": 250, "loss": 0.412, "samples_per_s": 182},
        {"step": 1000, "loss": 0.05, "samples_per_s": 1200},
    ]


def curve(losses, start=10, every=10):
    return [{"step": start + every * i, "loss": loss} for i, loss in enumerate(losses)]


def row(losses, steps=100, ema=100, success=50.0, se=7.0):
    return {
        "curve": curve(losses),
        "steps": steps,
        "ema_updates": ema,
        "pc_success": success,
        "pc_success_se": se,
        "avg_max_reward": success / 100,
        "avg_max_reward_se": se / 100,
    }


def test_curve_distance_skips_warmup_and_needs_common_steps():
    a, b = curve([9.0, 1.0, 1.0]), curve([0.0, 1.5, 0.5])
    assert curve_distance(a, b, after_step=10) == 0.5  # step 10 (9 vs 0) is warm-up
    with pytest.raises(ValueError, match="share no logged step"):
        curve_distance(a, curve([1.0], start=15), after_step=0)


def test_verdict_tells_noise_from_a_different_run():
    s0, s1 = [1.0, 0.8, 0.6, 0.5, 0.4], [1.1, 0.7, 0.65, 0.45, 0.42]
    same = verdict({"single_0": row(s0), "single_1": row(s1), "parallel_0": row(s1[:2] + s0[2:])}, 100)
    assert same["loss_within_noise"] and same["ema_once_per_step"]
    assert same["pc_success_within_one_se"]
    off = verdict(
        {
            "single_0": row(s0),
            "single_1": row(s1),
            "parallel_0": row([x + 0.2 for x in s0], ema=200, success=20.0),
        },
        100,
    )
    assert not off["loss_within_noise"]
    assert not off["ema_once_per_step"]  # the EMA advanced twice per step
    assert off["pc_success_parallel_0_minus_single_0"] == -30.0 and not off["pc_success_within_one_se"]


@pytest.mark.slow
def test_tiny_data_parallel_run_reports(tmp_path):
    make_tiny_pusht_dataset(tmp_path / "data")
    config = json.loads(shipped_configs.path("pusht_state_cpu").read_text())
    config["policy"].update(
        down_dims=[16, 32], diffusion_step_embed_dim=16, n_chunks=2, num_inference_steps=8
    )
    config["policy"]["scheduler_warmup_steps"] = 0
    (tmp_path / "tiny.json").write_text(json.dumps(config))
    out = tmp_path / "out"
    args = ["data-parallel", f"--config_path={tmp_path / 'tiny.json'}", f"--dataset_root={tmp_path / 'data'}"]
    args += ["--repo_id=local/tiny_pusht", "--batch_size=2", "--steps=4", "--log_freq=1", "--num_workers=0"]
    cli.main([*args, "--eval_episodes=1", f"--output_dir={out}"])
    report = json.loads((out / "data_parallel.json").read_text())
    rows = report["runs"]
    assert [(r["processes"], r["batch_size"]) for r in rows.values()] == [(1, 4), (1, 4), (2, 2)]
    assert all(r["steps"] == 4 and r["ema_updates"] == 4 for r in rows.values())
    assert [p["step"] for p in rows["parallel_1000"]["curve"]] == [1, 2, 3, 4]
    assert report["verdict"]["ema_once_per_step"]
    assert (out / "loss.png").stat().st_size > 0 and "parallel_1000" in (out / "data_parallel.md").read_text()
