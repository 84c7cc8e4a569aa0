"""The delay benchmark: the virtual clock's timing per mode (which chunk, built from which tick's
observation, runs at each tick) and the whole bench on gym-pusht with tiny policies."""

import json
import os
import subprocess
import sys

import pytest
import torch
from sdp_test_utils import PUSHT_KEYPOINT_STATS, save_tiny_policy, tiny_config, tiny_dp_config
from torch import nn

from lerobot_sdp.benchmarks.virtual_clock import DelayedControl

TB, B = 4, 3


class TickCodedPolicy(nn.Module):
    """A policy whose action i of the chunk requested at tick t is the number 100 t + i (both action
    dimensions), so that each executed action names its chunk's observation tick and its index."""

    def __init__(self, kind: str, max_delay: int = 0):
        super().__init__()
        self.config = tiny_config(n_action_steps=TB, max_delay=max_delay)
        if kind == "diffusion":
            from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

            self.config = DiffusionConfig(
                n_action_steps=TB,
                horizon=8,
                input_features=self.config.input_features,
                output_features=self.config.output_features,
            )
        self.committed: list[int] = []

    def reset(self) -> None:
        self.committed.clear()

    def predict_action_chunk(self, history, committed=None):
        tick = int(history["observation.state"][0, -1, 0])  # the newest frame carries its tick
        if committed is not None:
            self.committed.append(committed)
        values = 100 * tick + torch.arange(TB, dtype=torch.float32)
        return values.view(1, TB, 1).expand(B, TB, 2)


def drive(control: DelayedControl, ticks: int) -> list[tuple[int, int]]:
    """Run `ticks` control ticks; per tick the executed action as (observation tick, index)."""
    control.reset()
    out = []
    for tick in range(ticks):
        obs = {k: torch.full((B, *ft.shape), float(tick)) for k, ft in control.config.input_features.items()}
        action = control.select_action(obs)
        value = int(action[0, 0])
        out.append((value // 100, value % 100))
    return out


def test_blocking_holds_the_last_target_for_d_ticks_then_runs_the_stale_chunk():
    control = DelayedControl(TickCodedPolicy("diffusion"), "blocking", delay=2)
    ran = drive(control, 12)
    # chunk from tick 0 at once (episode start); at tick 4 nothing is left: request, hold 2 ticks
    assert ran[:4] == [(0, 0), (0, 1), (0, 2), (0, 3)]
    assert ran[4:6] == [(0, 3), (0, 3)] and ran[6:10] == [(4, 0), (4, 1), (4, 2), (4, 3)]
    assert ran[10:12] == [(4, 3), (4, 3)] and control.held_ticks == 4


def test_naive_async_diffusion_drops_the_actions_that_are_already_past():
    control = DelayedControl(TickCodedPolicy("diffusion"), "naive_async", delay=1)
    ran = drive(control, 9)
    # requested at tick 3 (1 left), ready at 4: its action 0 was for tick 3, so tick 4 runs action 1
    assert ran[:4] == [(0, 0), (0, 1), (0, 2), (0, 3)]
    assert ran[4:7] == [(3, 1), (3, 2), (3, 3)] and ran[7] == (6, 1)
    assert control.held_ticks == 0


@pytest.mark.parametrize("mode", ["naive_async", "delay_aware"])
def test_sdp_chunks_follow_the_actions_left_and_delay_aware_commits_them(mode):
    policy = TickCodedPolicy("sdp", max_delay=2)
    control = DelayedControl(policy, mode, delay=2)
    ran = drive(control, 12)
    # requested at tick 2 with 2 actions left, ready at 4, run after them: 2 ticks after its observation
    assert ran[:4] == [(0, 0), (0, 1), (0, 2), (0, 3)]
    assert ran[4:8] == [(2, 0), (2, 1), (2, 2), (2, 3)] and ran[8:12] == [(6, 0), (6, 1), (6, 2), (6, 3)]
    assert policy.committed == ([0, 2, 2, 2] if mode == "delay_aware" else [0, 0, 0, 0])  # ticks 0, 2, 6, 10
    assert control.held_ticks == 0 and control.chunks == 4


@pytest.mark.parametrize("history", ["full", "frame"])
def test_history_is_the_last_frames_or_the_newest_repeated(history):
    seen = []

    class Recording(TickCodedPolicy):
        def predict_action_chunk(self, history, committed=None):
            seen.append(history["observation.state"][0, :, 0].tolist())  # the ticks of its frames
            return super().predict_action_chunk(history, committed)

    drive(DelayedControl(Recording("sdp", max_delay=2), "naive_async", delay=1, history=history), 8)
    # requests at ticks 0 (the first frame repeated at an episode's start), 3 and 7
    assert seen == ([[0, 0], [2, 3], [6, 7]] if history == "full" else [[0, 0], [3, 3], [7, 7]])
    with pytest.raises(ValueError, match="Unknown history"):
        DelayedControl(Recording("sdp"), "naive_async", delay=1, history="two")


def test_at_zero_delay_every_mode_is_the_plain_loop():
    runs = [
        drive(DelayedControl(TickCodedPolicy(kind, max_delay=2), mode, delay=0), 12)
        for kind, mode in [("diffusion", "blocking"), ("diffusion", "naive_async"), ("sdp", "delay_aware")]
    ]
    assert runs[0] == runs[1] == runs[2] == [(4 * (t // 4), t % 4) for t in range(12)]


@pytest.mark.parametrize(
    "kind, mode, delay, match",
    [
        ("sdp", "delay_aware", 3, "max_delay=2, not 3"),
        ("diffusion", "delay_aware", 1, "needs an SDP policy"),
        ("sdp", "naive_async", TB, "whole chunk"),
        ("sdp", "sideways", 1, "Unknown mode"),
    ],
)
def test_impossible_cells_are_named(kind, mode, delay, match):
    with pytest.raises(ValueError, match=match):
        DelayedControl(TickCodedPolicy(kind, max_delay=2), mode, delay)


def save_tiny_dp(path):
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    cfg = tiny_dp_config()
    DiffusionPolicy(cfg).save_pretrained(path)
    for pipeline in make_pre_post_processors(cfg, dataset_stats=PUSHT_KEYPOINT_STATS):
        pipeline.save_pretrained(path)
    return path


def test_the_bench_runs_every_row_on_gym_pusht_and_resumes(tmp_path):
    sdp = save_tiny_policy(tmp_path / "sdp", max_delay=1)
    dp = save_tiny_dp(tmp_path / "dp")
    out = tmp_path / "bench"
    cmd = [
        sys.executable, "-m", "lerobot_sdp.benchmarks.cli", "delay",
        f"--policy=sdp={sdp}", f"--policy=dp={dp}", "--delays", "0", "2",
        "--n_episodes=2", "--batch_size=2", "--episode_length=12", "--num_threads=1", f"--output_dir={out}",
    ]  # fmt: skip
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": "egl"}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    rows = {c["row"] for c in results["cells"].values()}
    assert rows == {"sdp naive_async", "sdp delay_aware", "dp blocking", "dp naive_async"}
    assert "skipped" in results["cells"]["sdp delay_aware @ 2"]  # trained for max_delay=1 only
    cell = results["cells"]["dp blocking @ 2"]
    assert cell["n_episodes"] == 2 and 0.0 <= cell["avg_max_reward"] <= 1.0 and cell["held_ticks"] > 0
    assert (
        set(results["latency"]) == {"sdp", "dp"} and results["latency"]["dp"]["denoiser_calls_per_chunk"] == 4
    )
    assert (out / "delay.png").stat().st_size > 0 and "| dp blocking |" in (out / "results.md").read_text()
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert again.returncode != 0 and "--resume" in again.stderr  # nothing overwritten without a flag
    resumed = subprocess.run([*cmd, "--resume"], capture_output=True, text=True, timeout=600, env=env)
    assert (
        resumed.returncode == 0
        and json.loads((out / "results.json").read_text())["cells"] == results["cells"]
    )
