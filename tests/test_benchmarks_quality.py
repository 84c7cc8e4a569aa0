"""The quality benchmark's plumbing: two training steps, two episodes, through the real CLIs."""

import argparse
import json
import threading
import time
from pathlib import Path

import pytest
from sdp_test_utils import make_tiny_pusht_dataset

from lerobot_sdp.benchmarks import cli
from lerobot_sdp.benchmarks.curves import (
    checkpoint_steps,
    episode_stats,
    step_logs,
    train_wall_s,
    wall_time_at,
)
from lerobot_sdp.benchmarks.quality import (
    BUDGETS,
    PAPER_SCHEMES,
    ablation_runs,
    add_arguments,
    comparison_runs,
    default_output_dir,
    evaluation,
    horizon_control_runs,
    markdown,
    only,
    resolve_budget,
    run_in_parallel,
    warmstart_runs,
    with_sdp_flags,
    with_step_conditioning,
)


def tiny_quality_args(tmp_path):
    """The tiny budget on the tiny Push-T dataset in tmp_path/data, into tmp_path/q."""
    out, data = str(tmp_path / "q"), str(tmp_path / "data")
    return [
        "quality",
        "--budget",
        "tiny",
        "--output_dir",
        out,
        "--dataset_repo_id",
        "local/tiny_pusht",
        "--dataset_root",
        data,
    ]


def test_tiny_comparison_runs_resumes_and_reports(tmp_path, capsys):
    make_tiny_pusht_dataset(tmp_path / "data")
    common = [
        *tiny_quality_args(tmp_path),
        "--curve_every",
        "1",
        "--eval_jobs",
        "2",
    ]
    # LeRobot's DP and the SDP farthest from it (SDP h = 2 runs in the robomimic test)
    argv = [*common, "--runs", "comparison", "--only", "dp", "sdp_h4", "--sweep"]
    cli.main(argv)
    report = json.loads((tmp_path / "q" / "results.json").read_text())
    rows = report["rows"]
    assert set(rows) == {"dp", "sdp_h4"}
    n = BUDGETS["tiny"].num_inference_steps
    assert rows["dp"]["denoiser_calls_per_chunk"] == n  # counted with hooks, not inferred
    assert rows["sdp_h4"]["denoiser_calls_per_chunk"] == n / 4
    for row in rows.values():
        assert row["n_episodes"] == 2 and 0 <= row["avg_max_reward"] <= 1 and row["train_wall_s"] > 0
    assert "| sdp_h4 |" in (tmp_path / "q" / "results.md").read_text()
    for row in rows.values():  # a checkpoint per step, each evaluated on the same episodes
        assert [p["step"] for p in row["curve"]] == [1, 2]
        assert all(p["n_episodes"] == 2 and p["train_wall_s"] >= 0 for p in row["curve"])
        assert row["curve"][-1]["avg_max_reward"] == row["avg_max_reward"]  # the last point is the run's eval
    assert (tmp_path / "q" / "curves.png").stat().st_size > 10_000
    sweep = report["sweep"]  # the final models again at several samplers, calls counted
    dp_samplers = ["DDPM100", "DDIM16", "DDIM10", "DDIM8", "DDIM5", "DDIM4", "DDIM2"]
    assert [p["sampler"] for p in sweep["dp"]] == dp_samplers
    assert [p["denoiser_calls_per_chunk"] for p in sweep["dp"]] == [100, 16, 10, 8, 5, 4, 2]
    for p in sweep["dp"]:  # each point is its own sampler's evaluation
        info = json.loads(
            (tmp_path / "q" / "runs" / "dp" / "sweep" / p["sampler"] / "eval_info.json").read_text()
        )
        assert p["avg_max_reward"] == pytest.approx(info["overall"]["avg_max_reward"])
    assert [p["denoiser_calls_per_chunk"] for p in sweep["sdp_h4"]] == [25, 4, 2, 1]
    assert (tmp_path / "q" / "cost.png").stat().st_size > 10_000
    # the same command again resumes: nothing is retrained, the status says so
    capsys.readouterr()
    cli.main([*argv, "--status"])
    out = capsys.readouterr().out
    assert out.count("evaluated") == 2
    # the same model on other episodes: not retrained, evaluated and reported beside the default ones
    train_log = (tmp_path / "q" / "runs" / "dp" / "train.log").read_text()
    cli.main([*common, "--runs", "comparison", "--only", "dp", "--eval_seed", "7", "--sweep"])
    held_out = json.loads((tmp_path / "q" / "eval_seed7" / "results.json").read_text())
    assert held_out["eval_seed"] == 7 and set(held_out["rows"]) == {"dp"}
    assert [p["sampler"] for p in held_out["sweep"]["dp"]] == dp_samplers
    assert (tmp_path / "q" / "eval_seed7" / "cost.png").stat().st_size > 10_000
    assert (tmp_path / "q" / "runs" / "dp" / "train.log").read_text() == train_log
    for eval_log in ("eval.log", "curve/000001.log", "sweep/DDIM2.log"):
        log = (tmp_path / "q" / "runs" / "dp" / "eval_seed7" / eval_log).read_text()
        assert "'seed': 7," in log and "'seed': 100000," not in log, eval_log
    default = json.loads((tmp_path / "q" / "results.json").read_text())
    assert default["rows"] == rows and default["sweep"] == sweep
    # another episode count on the same seed: its own folder, not the 2-episode evaluation reused
    cli.main([*common, "--runs", "comparison", "--only", "dp", "--eval_seed", "7", "--n_episodes", "1"])
    one = json.loads((tmp_path / "q" / "eval_seed7_1episodes" / "results.json").read_text())
    assert one["rows"]["dp"]["n_episodes"] == 1 and [p["n_episodes"] for p in one["rows"]["dp"]["curve"]] == [
        1,
        1,
    ]
    assert (
        json.loads((tmp_path / "q" / "eval_seed7" / "results.json").read_text())["rows"] == held_out["rows"]
    )
    assert (tmp_path / "q" / "runs" / "dp" / "train.log").read_text() == train_log
    # warm starts from the trained DP: fine-tuned runs log what they copied, scratch runs copy nothing
    cli.main([*common, "--runs", "warmstart", "--only", "warm_flatten", "warm_film", "scratch_film_short"])
    rows = json.loads((tmp_path / "q" / "results.json").read_text())["rows"]
    assert {"warm_flatten", "warm_film", "scratch_film_short"} <= set(rows)
    for name in ("warm_flatten", "warm_film"):
        log = (tmp_path / "q" / "runs" / name / "train.log").read_text()
        assert "Warm start from the Diffusion Policy checkpoint" in log and "copied" in log
    assert "Warm start" not in (tmp_path / "q" / "runs" / "scratch_film_short" / "train.log").read_text()
    assert "### Warm start from the trained DP" in (tmp_path / "q" / "results.md").read_text()
    # another run set in the same folder keeps the comparison's sweep
    assert json.loads((tmp_path / "q" / "results.json").read_text())["sweep"] == sweep
    assert "### Quality against cost" in (tmp_path / "q" / "results.md").read_text()


def test_eval_seed_must_be_a_seed(tmp_path):
    with pytest.raises(SystemExit, match="--eval_seed must be at least 0"):
        cli.main(["quality", "--budget", "tiny", "--eval_seed", "-1", "--output_dir", str(tmp_path)])


def test_other_episodes_are_evaluated_into_a_folder_named_for_them():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    budget = BUDGETS["robomimic_cpu"]  # 50 episodes from seed 1000

    def episodes(*argv):
        return evaluation(parser.parse_args(["--env", "robomimic", *argv]), budget)

    own = episodes()
    assert (own.seed, own.n, own.seed_dir) == (1000, 50, "")
    assert "--eval.n_episodes=50" in own.eval_args and "--seed=1000" in own.eval_args
    fresh = episodes("--eval_seed", "5000", "--n_episodes", "100")
    assert (fresh.seed_dir, str(fresh)) == ("eval_seed5000_100episodes", "100 episodes from seed 5000")
    assert "--eval.n_episodes=100" in fresh.eval_args and "--seed=5000" in fresh.eval_args
    assert episodes("--eval_seed", "5000").seed_dir == "eval_seed5000"
    assert episodes("--n_episodes", "100").seed_dir == "eval_seed1000_100episodes"
    assert episodes("--n_episodes", "50").seed_dir == ""


def test_n_episodes_must_be_positive(tmp_path):
    with pytest.raises(SystemExit, match="--n_episodes must be at least 1, got 0"):
        cli.main(["quality", "--budget", "tiny", "--n_episodes", "0", "--output_dir", str(tmp_path)])


def test_warm_start_runs_need_the_trained_dp(tmp_path):
    with pytest.raises(SystemExit, match="run `--runs comparison` with this --output_dir first"):
        cli.main(["quality", "--budget", "tiny", "--runs", "warmstart", "--output_dir", str(tmp_path)])


def test_ablations_share_one_model_for_the_primers():
    runs = {r.name: r for r in ablation_runs(BUDGETS["cpu"], "cpu")}
    assert {f"scheme_{k}" for k in PAPER_SCHEMES} <= set(runs)
    for primer in ("zero", "constant", "denoise"):
        run = runs[f"primer_{primer}"]
        assert run.model_run == "scheme_cw80_const20" and run.eval_overrides == {"action_primer": primer}
    assert "--policy.noise_schemes.independent=0.67" in runs["scheme_ind67_lin33"].policy_args
    assert all(r.steps == BUDGETS["cpu"].ablation_steps for r in runs.values())


def test_only_selects_runs_with_the_models_they_evaluate(tmp_path, capsys):
    comparison = comparison_runs(BUDGETS["cpu"], "cpu")
    assert [r.name for r in only(comparison, ["sdp_h4"])] == ["sdp_h4"]
    assert [r.name for r in only(comparison, ["sdp_h4", "dp"])] == ["dp", "sdp_h4"]
    assert only(comparison, None) == comparison
    ablations = ablation_runs(BUDGETS["cpu"], "cpu")
    assert [r.name for r in only(ablations, ["primer_zero"])] == ["scheme_cw80_const20", "primer_zero"]
    with pytest.raises(SystemExit, match=r"--only sdp_h8: no such run .* dp, sdp_h2, sdp_h4"):
        only(comparison, ["sdp_h8"])
    cli.main(["quality", "--budget", "tiny", "--only", "sdp_h2", "--status", "--output_dir", str(tmp_path)])
    printed = capsys.readouterr().out
    assert [line.split()[0] for line in printed.splitlines() if line.strip()] == ["sdp_h2"]


def test_step_conditioning_and_sdp_flags_reach_the_sdp_runs_only(tmp_path):
    runs = comparison_runs(BUDGETS["cpu"], "cpu") + warmstart_runs(BUDGETS["cpu"], "cpu", tmp_path)
    film = {r.name: r for r in with_step_conditioning(runs, "film_per_slot")}
    flag = "--policy.step_conditioning=film_per_slot"
    for name in ("sdp_h2", "sdp_h4", "warm_flatten", "scratch_flatten_short"):
        assert film[name].policy_args.count(flag) == 1
    assert flag not in film["dp"].policy_args
    flat = {r.name: r for r in with_step_conditioning(runs, "flatten")}
    assert flag in flat["warm_film"].policy_args  # a run that chose its encoder keeps it
    assert "--policy.step_conditioning=flatten" not in flat["warm_film"].policy_args
    assert with_step_conditioning(runs, None) == with_sdp_flags(runs, []) == runs
    # a recipe carried to the comparison: every SDP run, not DP, in place of the run's own value
    recipe = ["--policy.min_snr_gamma=5.0", "--policy.noise_schemes.constant=0.5"]
    carried = {r.name: r for r in with_sdp_flags(runs, recipe)}
    assert recipe[0] in carried["sdp_h4"].policy_args and recipe[0] not in carried["dp"].policy_args
    h4 = carried["sdp_h4"].policy_args
    assert h4.count(recipe[1]) == 1 and not any(
        a.startswith("--policy.noise_schemes.constant=0.2") for a in h4
    )
    assert "--policy.noise_schemes.chunkwise=0.8" in h4  # the keys not named stay
    with pytest.raises(SystemExit):
        cli.main(["quality", "--step_conditioning", "film", "--status"])
    with pytest.raises(SystemExit, match=r"--policy\.KEY=VALUE"):
        cli.main(["quality", "--sdp_flag=min_snr_gamma=5", "--status", "--output_dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="pass --output_dir"):
        cli.main(["quality", "--sdp_flag=--policy.min_snr_gamma=5", "--status"])
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    film_can = ["--env", "robomimic", "--task", "PickPlaceCan", "--step_conditioning", "film_per_slot"]
    args = parser.parse_args(film_can)
    assert default_output_dir(args, "robomimic_cpu_24000steps") == Path(
        "outputs/quality_pickplacecan_robomimic_cpu_24000steps_film_per_slot"
    )
    assert default_output_dir(parser.parse_args([]), "cpu") == Path("outputs/quality_cpu")


def test_parallel_runs_overlap_and_primers_wait_for_their_model():
    runs = ablation_runs(BUDGETS["tiny"], "cpu")
    lock, active, events = threading.Lock(), [0], []

    def fake_execute(run):
        with lock:
            active[0] += 1
            events.append(("start", run.name, active[0]))
        time.sleep(0.05)
        with lock:
            active[0] -= 1
            events.append(("end", run.name, active[0]))
        return {"run": run.name}

    rows = list(run_in_parallel(runs, fake_execute, jobs=3))
    assert sorted(r["run"] for r in rows) == sorted(r.name for r in runs)
    assert max(n for kind, _, n in events if kind == "start") == 3  # three at once, never more
    order = [(kind, name.split("_")[0]) for kind, name, _ in events]
    last_training_end = max(i for i, e in enumerate(order) if e == ("end", "scheme"))
    first_primer_start = min(i for i, e in enumerate(order) if e == ("start", "primer"))
    assert first_primer_start > last_training_end  # the primers evaluate a finished model
    with pytest.raises(SystemExit, match="--jobs must be at least 1"):
        cli.main(["quality", "--budget", "tiny", "--jobs", "0", "--output_dir", "unused"])
    with pytest.raises(SystemExit, match="--eval_jobs must be at least 1"):
        cli.main(["quality", "--budget", "tiny", "--eval_jobs", "0", "--output_dir", "unused"])


def test_comparison_trains_every_policy_the_same_way():
    runs = comparison_runs(BUDGETS["cpu"], "cpu")
    shared = [
        set(
            a
            for a in r.policy_args
            if not a.startswith(
                (
                    "--policy.type",
                    "--policy.n_chunks",
                    "--policy.horizon",
                    "--policy.noise_schemes",
                    "--policy.use_ema",
                    "--policy.pretrained",
                )
            )
        )
        for r in runs
    ]
    assert shared[0] == shared[1] == shared[2]
    assert len({r.steps for r in runs}) == 1


def test_horizon_controls_are_dp_as_far_ahead_as_sdp_and_lerobot_accepts_them():
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    budget = BUDGETS["cpu"]
    dp = comparison_runs(budget, "cpu")[0]
    runs = horizon_control_runs(budget, "cpu")
    # SDP h = 4 predicts 1 past + 32 future actions, h = 2 1 + 16; LeRobot wants multiples of 8 here
    assert [r.name for r in runs] == ["dp_horizon40", "dp_horizon24"]
    for run, horizon in zip(runs, (40, 24), strict=True):
        assert set(run.policy_args) ^ set(dp.policy_args) == {
            "--policy.horizon=16",
            f"--policy.horizon={horizon}",
        }
        assert run.steps == dp.steps
        DiffusionConfig(horizon=horizon, down_dims=budget.down_dims)  # no ValueError
    with pytest.raises(ValueError, match="multiple of the downsampling factor"):
        DiffusionConfig(horizon=36, down_dims=budget.down_dims)  # SDP h = 4's own horizon


def test_markdown_puts_the_papers_numbers_beside_ours():
    row = {
        "avg_max_reward": 0.5,
        "pc_success": 10.0,
        "denoiser_calls_per_chunk": 50,
        "latency_per_chunk_ms": 3.0,
        "train_wall_s": 1.0,
        "steps": 2,
        "n_episodes": 2,
    }
    text = markdown({"dp": row, "scheme_linear": row}, "tiny", BUDGETS["tiny"])
    assert "| scheme_linear | 0.500 | 10.0 | 0.36 |" in text and "| dp | 0.500 |" in text


def test_steps_flag_is_a_labelled_reduced_budget():
    parser = cli.build_parser()
    name, budget = resolve_budget(parser.parse_args(["quality", "--budget", "cpu", "--steps", "3000"]))
    assert name == "cpu_3000steps" and budget.steps == budget.ablation_steps == 3000
    assert budget.batch_size == BUDGETS["cpu"].batch_size  # everything else stays the budget's
    assert resolve_budget(parser.parse_args(["quality", "--budget", "cpu"])) == ("cpu", BUDGETS["cpu"])
    robomimic = parser.parse_args(["quality", "--env", "robomimic"])
    assert resolve_budget(robomimic) == ("robomimic_cpu", BUDGETS["robomimic_cpu"])


def test_robomimic_comparison_on_scripted_demonstrations(tmp_path):
    """`--env robomimic`: demonstrations recorded once into the output folder, every policy trained
    on them and evaluated in the robomimic env on the same episodes, at its own denoiser cost."""
    pytest.importorskip(
        "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
    )
    out = tmp_path / "q"
    argv = ["quality", "--env", "robomimic", "--task", "Lift", "--budget", "tiny", "--num_demos", "2"]
    cli.main([*argv, "--only", "dp", "sdp_h2", "--output_dir", str(out)])
    report = json.loads((out / "results.json").read_text())
    assert report["task"] == "robomimic Lift (low-dim)" and report["eval_seed"] == 1000
    recording = json.loads((out / "data" / "recording.json").read_text())
    assert recording["successes"] == 2 and recording["repo_id"] == "local/scripted_lift"
    n = BUDGETS["tiny"].num_inference_steps
    calls = {name: row["denoiser_calls_per_chunk"] for name, row in report["rows"].items()}
    assert calls == {"dp": n, "sdp_h2": n / 2}  # counted with hooks, not inferred
    for name, row in report["rows"].items():
        assert row["n_episodes"] == 2
        config = json.loads((out / "runs" / name / "eval" / "eval_info.json").read_text())
        log = (out / "runs" / name / "eval.log").read_text()
        assert "robomimic" in log and "'task': 'Lift'" in log, name
        assert config["overall"]["n_episodes"] == 2


def test_wall_time_skips_the_stop_between_sessions(tmp_path):
    """Two sessions of one run, stopped for an hour after step 200: the hour is not training."""
    log = tmp_path / "train.log"
    lines = [
        "INFO 2026-11-23 10:00:10 ot_train.py:641 step:100 smpl:6K updt_s:0.1 data_s:0.1",
        "INFO 2026-11-23 10:00:20 ot_train.py:641 step:200 smpl:13K updt_s:0.1 data_s:0.1",
        "INFO 2026-11-23 11:00:20 ot_train.py:641 step:300 smpl:19K updt_s:0.1 data_s:0.1",
        "INFO 2026-11-23 11:00:30 ot_train.py:641 step:400 smpl:26K updt_s:0.1 data_s:0.1",
        "INFO 2026-11-23 11:00:40 ot_train.py:641 step:1.5K smpl:96K updt_s:0.1 data_s:0.1",
    ]
    log.write_text("\n".join(lines) + "\n")
    marks = step_logs(log)
    assert [s for _, s in marks] == [100, 200, 300, 400, 1500]
    # 0.1 s per step everywhere it was measured; steps 0-100 and 200-300 charged at that rate
    assert wall_time_at(marks, 400) == pytest.approx(40.0)
    assert wall_time_at(marks, 200) == pytest.approx(20.0)


def test_a_runs_wall_time_leaves_out_the_pause_its_clock_counted(tmp_path):
    """The run's row reads its time from the step logs, as a curve point does: the hour stopped after
    step 200 is not charged, though the wall clock (3,640 s) counted it; no step logs, the clock."""
    log = tmp_path / "train.log"
    lines = [f"INFO 2026-11-23 10:00:{10 * k:02d} ot_train.py:641 step:{100 * k} smpl:1K" for k in (1, 2)]
    lines += [f"INFO 2026-11-23 11:00:{10 * k:02d} ot_train.py:641 step:{100 * k} smpl:1K" for k in (3, 4)]
    log.write_text("\n".join(lines) + "\n")
    assert train_wall_s(log, 400, clock_s=3640.0) == pytest.approx(40.0)
    assert train_wall_s(tmp_path / "missing.log", 400, clock_s=3640.0) == 3640.0


def test_exact_steps_come_from_the_progress_bar_after_a_resume(tmp_path):
    """LeRobot rounds `step:` to a thousand; its progress bar counts the steps left after a resume.
    A run of 3,000 steps resumed at 2,000: the bar reads n/1000, the exact step is 2,000 + n."""
    log = tmp_path / "train.log"
    bar = "Training:  10%|█         | {n}/{total} [00:40<05:00,  5.00step/s]"
    lines = [
        bar.format(n=200, total=3000) + "INFO 2026-11-23 10:00:40 ot_train.py:641 step:200 smpl:13K",
        bar.format(n=400, total=3000) + "INFO 2026-11-23 10:01:20 ot_train.py:641 step:400 smpl:26K",
        bar.format(n=200, total=1000) + "INFO 2026-11-23 12:00:20 ot_train.py:641 step:2K smpl:141K",
        bar.format(n=400, total=1000) + "INFO 2026-11-23 12:01:00 ot_train.py:641 step:2K smpl:154K",
    ]
    log.write_text("\n".join(lines) + "\n")
    assert [s for _, s in step_logs(log, final_step=3000)] == [200, 400, 2200, 2400]
    assert [s for _, s in step_logs(log)] == [200, 400, 2000, 2000]  # rounded: the interval is lost
    marks = step_logs(log, final_step=3000)
    # 0.2 s per step measured; the steps no interval covers (0-200, 400-2200) charged at that rate
    assert wall_time_at(marks, 2400) == pytest.approx(2400 * 0.2)


def test_episode_stats_gives_standard_errors(tmp_path):
    info = {
        "overall": {"avg_max_reward": 0.5, "pc_success": 50.0},
        "per_task": [
            {"metrics": {"max_rewards": [0.0, 1.0, 0.5, 0.5], "successes": [False, True, True, False]}}
        ],
    }
    (tmp_path / "eval_info.json").write_text(json.dumps(info))
    stats = episode_stats(tmp_path)
    assert stats["avg_max_reward"] == pytest.approx(0.5) and stats["n_episodes"] == 4
    assert stats["avg_max_reward_se"] == pytest.approx((1 / 6) ** 0.5 / 2)  # sample std / sqrt(n)
    assert stats["pc_success"] == pytest.approx(50.0) and stats["pc_success_se"] == pytest.approx(25.0)


def test_checkpoint_steps_lists_multiples_only(tmp_path):
    for name in ("000500", "001000", "001500", "002000", "last"):
        (tmp_path / "checkpoints" / name).mkdir(parents=True)
    assert checkpoint_steps(tmp_path, 1000) == [1000, 2000]


def test_paper_budget_is_the_shipped_paper_config(tmp_path, monkeypatch):
    from lerobot_sdp import shipped_configs
    from lerobot_sdp.benchmarks import quality

    paper = quality.paper_budget()  # the authors' settings (docs/algorithm.md, section 9)
    assert (paper.steps, paper.batch_size, paper.down_dims, paper.embed_dim) == (
        100_000,
        256,
        (256, 512, 1024),
        256,
    )
    assert (paper.lr, paper.num_inference_steps, paper.scheduler) == (1e-4, 100, "DDPM")
    edited = json.loads(shipped_configs.path("pusht_state_paper").read_text())
    edited["steps"], edited["policy"]["down_dims"] = 5_000, [8, 16]
    (tmp_path / "pusht_state_paper.json").write_text(json.dumps(edited))
    monkeypatch.setattr(shipped_configs, "root", lambda: tmp_path)
    assert quality.paper_budget().steps == 5_000 and quality.paper_budget().down_dims == (8, 16)


def test_every_screen_candidate_sets_its_option_and_nothing_else():
    import draccus

    from lerobot_sdp import SDPConfig
    from lerobot_sdp.benchmarks.quality import screen_runs
    from lerobot_sdp.noise_schemes import NoiseCurriculum, NoiseSchemeWeights

    budget = resolve_budget(argparse.Namespace(budget="robomimic_cpu", env="robomimic", steps=8000))[1]
    runs = {r.name: r for r in screen_runs(budget, "cpu")}
    assert "--policy.type=diffusion" in runs["dp"].policy_args and runs["dp"].steps == 8000

    def parsed(name):
        flags = [a.removeprefix("--policy.") for a in runs[name].policy_args if a != "--policy.type=sdp"]
        return draccus.parse(SDPConfig, args=[f"--{a}" for a in flags])

    base = parsed("sdp_h2")
    assert base.n_chunks == 2 and not base.use_ema and base.noise_schemes.as_dict()["chunkwise"] == 0.8
    changed = {
        "screen_training_table": {"chunkwise_grid": "training_table"},
        "screen_curriculum_switch": {"noise_curriculum": NoiseCurriculum(constant_steps=2000)},
        "screen_curriculum_ramp": {"noise_curriculum": NoiseCurriculum(ramp_steps=4000)},
        "screen_min_snr5": {"min_snr_gamma": 5.0},
        "screen_ema": {"use_ema": True},
        "screen_independent_chunks": {
            "noise_schemes": NoiseSchemeWeights(constant=0.2, chunkwise=0.6, independent_chunks=0.2)
        },
    }
    for name, fields in changed.items():
        cfg = parsed(name)
        for field, value in fields.items():
            assert getattr(cfg, field) == value, name
            setattr(cfg, field, getattr(base, field))
        assert cfg == base, name  # every other setting as the default recipe's
    const50 = parsed("screen_const50")
    assert const50.noise_schemes.as_dict() == {
        "constant": 0.5,
        "linear": 0.0,
        "independent": 0.0,
        "chunkwise": 0.5,
        "independent_chunks": 0.0,
    }


def test_tiny_screen_trains_the_candidates_probes_them_and_resumes(tmp_path, capsys):
    make_tiny_pusht_dataset(tmp_path / "data")
    make_tiny_pusht_dataset(tmp_path / "held_out", n_episodes=1, length=20, seed=1)
    argv = [*tiny_quality_args(tmp_path), "--runs", "screen", "--only", "screen_curriculum_switch"]
    argv += ["screen_min_snr5", "--probe_dataset_root", str(tmp_path / "held_out")]
    argv += ["--probe_repo_id", "local/tiny_pusht"]
    cli.main(argv)
    report = json.loads((tmp_path / "q" / "results.json").read_text())
    assert set(report["rows"]) == {"screen_curriculum_switch", "screen_min_snr5"}
    assert {r["policy"] for r in report["probe"]["rows"]} == {"screen_curriculum_switch", "screen_min_snr5"}
    assert report["probe"]["settings"]["n_windows"] == 20
    text = (tmp_path / "q" / "results.md").read_text()
    assert "### Screen of the training recipes (2 steps each)" in text and "| screen_min_snr5 |" in text
    assert "### Probe: the final models with true and shuffled observations" in text
    config = json.loads(
        (tmp_path / "q/runs/screen_min_snr5/train/checkpoints/last/pretrained_model/config.json").read_text()
    )
    assert config["min_snr_gamma"] == 5.0
    capsys.readouterr()
    cli.main([*argv, "--status"])
    assert capsys.readouterr().out.count("evaluated") == 2


def test_runs_trained_at_once_share_the_cores(tmp_path, monkeypatch):
    """`--jobs 2` tells each training it runs beside another, so that the two do not each start a
    thread per core (four OpenMP pools spinning on two cores)."""
    from lerobot_sdp.benchmarks import quality

    class StopError(Exception):
        pass

    seen = []

    def fake_train(*args, concurrent=1, precision=None, **kwargs):
        seen.append((concurrent, precision))
        raise StopError

    make_tiny_pusht_dataset(tmp_path / "data")
    monkeypatch.setattr(quality, "train", fake_train)
    for jobs, precision in (("1", []), ("2", ["--precision", "auto"])):
        with pytest.raises(StopError):
            args = ["--runs", "comparison", "--only", "dp", "--jobs", jobs, *precision]
            cli.main([*tiny_quality_args(tmp_path), *args])
    assert seen == [(1, "fp32"), (2, "auto")]  # the cores shared; fp32 unless asked, as published
