#!/usr/bin/env python
"""Mutation check of the streaming core: does the test suite notice single-line bugs?

    .venv/bin/python .ci/mutants.py                 # every mutant (or: make mutation)
    .venv/bin/python .ci/mutants.py --list          # check the list against the sources, print it
    .venv/bin/python .ci/mutants.py --only B04,S11  # some of them
    .venv/bin/python .ci/mutants.py --only F01 --tests tests/test_policy_server_faults.py  # quick check

Each mutant is one textual change (file, exact original text, replacement) to buffer.py,
schedule.py, geometry.py, noise_schemes.py, the step-embedding cache of unet.py, the primer,
NaN-guard, inference-delay, autocast and training-recipe lines of modeling_sdp.py, loss_weighting.py,
the probe (benchmarks/probe.py) and the screen's flags, the per-rank noise streams of
data_parallel.py, the policy server's plan and timing, the delay bench's virtual clock and
pusht_sim's wall clock. The script
copies the package and its tests to a temporary directory (the working tree is never modified, so
an interrupted run leaves nothing behind), checks that the unmutated copy passes, then applies one
mutant at a time to the copy and runs the core tests with ``-x -q``. A mutant is *killed* when
the tests fail, *survived* when they pass.

Mutants marked ``equivalent`` cannot change behaviour (the reason is given); they are run anyway, to
show that they survive. The exit code is 1 when a behaviour-changing mutant survives or an
"equivalent" one is killed (the equivalence claim was wrong), 2 when the list no longer matches
the sources (an original text is missing or ambiguous) or the unmutated copy fails its tests.
Reports: <out>/report.json and <out>/report.md (default outputs/mutants/, git-ignored).
"""

import argparse
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = "lerobot_sdp"
COPIED = [PKG, "tests", "configs", "docs/upstream", "pyproject.toml", "lerobot_policy_sdp.py", "README.md"]
# Order matters only for speed (-x stops at the first failure): the buffer-contents tests kill most
# mutants of every module within seconds, the policy-level files are the slowest.
CORE_TESTS = [
    "tests/test_buffer_contents.py",
    "tests/test_geometry.py",
    "tests/test_schedule.py",
    "tests/test_noise_schemes.py",
    "tests/test_buffer.py",
    "tests/test_modeling_sdp.py",
    "tests/test_streaming_step.py",
    "tests/test_policy_server.py",
    "tests/test_protocol_pickle.py",
    "tests/test_policy_server_faults.py",
    "tests/test_model_card.py",
    "tests/test_sampling_modes.py",
    "tests/test_benchmarks_animation.py",
    "tests/test_benchmarks_compiled.py",
    "tests/test_rtc.py",
    "tests/test_benchmarks_delay.py::test_blocking_holds_the_last_target_for_d_ticks_then_runs_the_stale_chunk",
    "tests/test_benchmarks_delay.py::test_naive_async_diffusion_drops_the_actions_that_are_already_past",
    "tests/test_benchmarks_delay.py::test_sdp_chunks_follow_the_actions_left_and_delay_aware_commits_them",
    "tests/test_benchmarks_delay.py::test_history_is_the_last_frames_or_the_newest_repeated",
    "tests/test_pusht_robot.py::test_the_env_advances_with_the_wall_clock_and_a_stall_holds_the_last_target",
    "tests/test_warm_start.py::test_checkpoint_that_does_not_fit_is_a_clear_error",
    "tests/test_mixed_precision.py",
    "tests/test_data_parallel.py::test_one_process_keeps_the_global_stream",
    "tests/test_data_parallel.py::test_every_rank_draws_its_own_training_noise_reproducibly",
    "tests/test_memory_dataset.py",
    "tests/test_lerobot_cli.py::test_training_threads_follow_the_dataloader_workers",
    "tests/test_lerobot_cli.py::test_run_logged_gives_the_child_its_threads_unless_the_user_chose",
    "tests/test_lerobot_cli.py::test_a_training_beside_others_gets_its_share_of_the_cores",
    "tests/test_lerobot_cli.py::test_native_bf16_is_read_from_the_cpus_flags",
    "tests/test_lerobot_cli.py::test_precision_flags_turn_bf16_on_for_cpu_trainings_on_native_bf16_only",
    "tests/test_lerobot_cli.py::test_a_new_training_gets_the_precision_and_a_resumed_one_keeps_its_own",
    "tests/test_main_job.py::test_the_pusht_job_picks_its_precision_by_the_cpu_and_the_robomimic_job_trains_fp32",
    "tests/test_benchmarks_quality.py::test_runs_trained_at_once_share_the_cores",
    "tests/test_configuration_sdp.py",
    "tests/test_benchmarks_hardware_limit.py",
    "tests/test_benchmarks_train_profile.py",
    "tests/test_training_recipe.py",
    "tests/test_benchmarks_probe.py",
    "tests/test_benchmarks_quality.py::test_every_screen_candidate_sets_its_option_and_nothing_else",
    "tests/test_benchmarks_quality.py::test_step_conditioning_and_sdp_flags_reach_the_sdp_runs_only",
    "tests/test_benchmarks_quality.py::test_other_episodes_are_evaluated_into_a_folder_named_for_them",
    "tests/test_pusht_robot.py::test_a_reconnect_starts_a_new_episode",
    "tests/test_deployment_schedules.py",
]
_buffer_tests = {p.relative_to(REPO).as_posix() for p in (REPO / "tests").glob("test_buffer*.py")}
CORE_TESTS += sorted(_buffer_tests - set(CORE_TESTS))  # any later tests/test_buffer*.py


@dataclass(frozen=True)
class Mutant:
    id: str
    file: str  # relative to lerobot_sdp/
    original: str  # must occur exactly once in the file
    replacement: str
    description: str
    equivalent: str | None = None  # why it cannot change behaviour, for semantically equivalent mutants


M = Mutant
MUTANTS = [
    # --- buffer.py: shift, noise of primed / appended / past slots, executed slice, plan -------------
    M("B01", "buffer.py",
      "kept = sample[:, g.chunk_len : g.n_past + g.n_future]",
      "kept = sample[:, g.chunk_len - 1 : g.n_past + g.n_future - 1]",
      "shift by Tb - 1 slots instead of one chunk"),
    M("B02", "buffer.py",
      "kept = sample[:, g.chunk_len : g.n_past + g.n_future]",
      "kept = sample[:, : g.n_past + g.n_future - g.chunk_len]",
      "buffer not shifted at all"),
    M("B03", "buffer.py",
      "kept = sample[:, g.chunk_len : g.n_past + g.n_future]",
      "kept = sample[:, g.chunk_len + 1 : g.n_past + g.n_future + 1]",
      "shift by Tb + 1 slots (reads a padding slot, or runs off the end)"),
    M("B04", "buffer.py",
      "return a * clean + b * noise",
      "return clean",
      "past slots left clean but labelled noisy (the authors' bug)"),
    M("B05", "buffer.py",
      "a, b = start.sqrt_abar[..., : g.n_past, :], start.sqrt_one_minus_abar[..., : g.n_past, :]",
      "a, b = start.sqrt_abar[..., -1:, :], start.sqrt_one_minus_abar[..., -1:, :]",
      "past slots re-noised to level N (the last slot's) instead of chunk 0's"),
    M("B06", "buffer.py",
      "shift(geometry, sample, plan[0], noise.shift)",
      "shift(geometry, sample, plan[-1], noise.shift)",
      "past slots re-noised to the last step's level (k = 1) instead of chunk 0's start level"),
    M("B07", "buffer.py",
      "return a * clean + b * noise",
      "return b * clean + a * noise",
      "past re-noise with signal and noise scales swapped"),
    M("B08", "buffer.py",
      "tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]",
      "tail = torch.zeros_like(noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad])",
      "appended chunk is zeros, not N(0, I)"),
    M("B09", "buffer.py",
      "tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]",
      "tail = sample[:, g.horizon - g.chunk_len - g.n_pad :]",
      "appended chunk reuses the stale old last chunk instead of fresh noise"),
    M("B10", "buffer.py",
      "tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]",
      "tail = noise[:, g.n_past : g.n_past + g.chunk_len]",
      "padding slots not re-appended (buffer shrinks)"),
    M("B11", "buffer.py",
      "return sample[:, geometry.executed], shift(",
      "return sample[:, : geometry.chunk_len], shift(",
      "executed chunk read from slot 0, ignoring the past slots"),
    M("B12", "buffer.py",
      "self.schedule.add_noise(primer, gaussian_like(primer, generator), t)",
      "self.schedule.add_noise(primer, torch.zeros_like(primer), t)",
      "primer scaled to its levels but carries no noise"),
    M("B13", "buffer.py",
      "sample = self.schedule.add_noise(primer, gaussian_like(primer, generator), t)",
      "sample = gaussian_like(primer, generator)",
      "buffer starts from pure noise, the primer is ignored"),
    M("B14", "buffer.py",
      "t = self.plan(primer.device, primer.shape[0])[0].timesteps",
      "t = self.plan(primer.device, primer.shape[0])[-1].timesteps",
      "primer noised to the last step's levels instead of the start levels"),
    M("B15", "buffer.py",
      "schedule.coefficients((k_start - j).clamp(min=0), all_active",
      "schedule.coefficients((k_start - j - 1).clamp(min=0), all_active",
      "every reverse step one level too low (plan off by one)"),
    M("B16", "buffer.py",
      "schedule.coefficients((k_start - j).clamp(min=0), all_active",
      "schedule.coefficients(k_start - j, all_active",
      "clamp removed from the reverse plan: committed slots (level 0) are stepped to negative levels"),
    M("B17", "buffer.py",
      "self.schedule, k_start, self.geometry.steps_per_call, batch_size",
      "self.schedule, k_start, self.geometry.steps_per_call - 1, batch_size",
      "one denoiser call short per chunk (executed chunk left at k = 1)"),
    M("B18", "buffer.py",
      "gaussian_like(window, generator))",
      "gaussian_like(window))",
      "shift noise (re-noised past, new tail) drawn from the global RNG, not the generator"),
    M("B19", "buffer.py",
      "tail = noise[:, g.n_past : g.n_past + g.chunk_len + g.n_pad]",
      "tail = noise[:, : g.chunk_len + g.n_pad]",
      "the new tail reuses the past slots' re-noise draws (correlated noise)"),
    M("B20", "buffer.py",
      "noise=None if noise is None else noise[j]",
      "noise=None if noise is None else noise[0]",
      "DDPM adds the same step noise on every step of a call"),
    # --- geometry.py: staircase, slot chunks, padding, steps per call, executed slice -----------------
    M("G01", "geometry.py",
      "return (self.slot_chunk + 1) * self.steps_per_call",
      "return self.slot_chunk * self.steps_per_call + 1",
      "chunk i starts at the bottom of its band (i*s + 1) instead of (i+1)*s"),
    M("G02", "geometry.py",
      "return (self.slot_chunk + 1) * self.steps_per_call",
      "return (self.slot_chunk + 1) * self.steps_per_call - 1",
      "start levels one step too low"),
    M("G03", "geometry.py",
      "torch.zeros(self.n_past, dtype=torch.long),",
      "torch.ones(self.n_past, dtype=torch.long),",
      "past slots labelled chunk 1 instead of chunk 0"),
    M("G04", "geometry.py",
      "torch.full((self.n_pad,), self.n_chunks - 1, dtype=torch.long),",
      "torch.zeros(self.n_pad, dtype=torch.long),",
      "padding slots labelled chunk 0 instead of the last chunk"),
    M("G05", "geometry.py",
      "future = torch.arange(self.n_future) // self.chunk_len",
      "future = torch.arange(self.n_future) // self.n_chunks",
      "future slots grouped into chunks by h instead of Tb"),
    M("G06", "geometry.py",
      "return -(-length // multiple) * multiple",
      "return (length // multiple + 1) * multiple",
      "horizon padding adds a block even when the length already fits"),
    M("G07", "geometry.py",
      "return self.num_inference_steps // self.n_chunks",
      "return self.num_inference_steps // self.chunk_len",
      "steps per call N / Tb instead of N / h"),
    M("G08", "geometry.py",
      "return slice(self.n_past, self.n_past + self.chunk_len)",
      "return slice(self.n_past + 1, self.n_past + 1 + self.chunk_len)",
      "executed slice one slot late"),
    # --- schedule.py: k -> t table, clean end, coefficients, clamps, active guard ----------------------
    M("S01", "schedule.py",
      "timesteps = torch.as_tensor(scheduler.timesteps, dtype=torch.long).flip(0)",
      "timesteps = torch.as_tensor(scheduler.timesteps, dtype=torch.long)",
      "k -> t table descending (k = 1 maps to the noisiest timestep)"),
    M("S02", "schedule.py",
      "return self.timestep_table[k]",
      "return self.timestep_table[k - 1]",
      "k -> t table read one entry low (off by one)"),
    M("S03", "schedule.py",
      "return self.abar_shifted[t + 1].unsqueeze(-1)",
      "return self.abar_shifted[t].unsqueeze(-1)",
      "abar gathered one timestep off"),
    M("S04", "schedule.py",
      "final = float(scheduler.final_alpha_cumprod) if self.is_ddim else 1.0",
      "final = 1.0",
      "clean-end abar ignores DDIM's final_alpha_cumprod (set_alpha_to_one=False)"),
    M("S05", "schedule.py",
      "final = float(scheduler.final_alpha_cumprod) if self.is_ddim else 1.0",
      "final = float(scheduler.alphas_cumprod[0])",
      "clean end is abar_0 instead of 1: executed actions keep residual noise"),
    M("S06", "schedule.py",
      "return abar.sqrt() * x0 + (1 - abar).sqrt() * eps",
      "return abar * x0 + (1 - abar) * eps",
      "forward process without square roots"),
    M("S07", "schedule.py",
      "self.train_timesteps((k - 1).clamp(min=0))",
      "self.train_timesteps((k - 2).clamp(min=0))",
      "each step targets two levels down"),
    M("S08", "schedule.py",
      "self.train_timesteps((k - 1).clamp(min=0))",
      "self.train_timesteps(k - 1)",
      "clamp removed from t_prev",
      equivalent="k - 1 < 0 only where k = 0, an inactive slot whose result torch.where discards"),
    M("S09", "schedule.py",
      "return prev if c.active is None else torch.where(c.active, prev, sample)",
      "return prev",
      "torch.where(active) guard removed: clean slots (k = 0) are stepped"),
    M("S10", "schedule.py",
      "active = (k > 0).unsqueeze(-1)",
      "active = (k > 1).unsqueeze(-1)",
      "the last step (k = 1 -> 0) is skipped"),
    M("S11", "schedule.py",
      "x0 = x0.clamp(-self.clip_range, self.clip_range)",
      "x0 = x0",
      "x0 clipping removed"),
    M("S12", "schedule.py",
      "x0 = (sample - c.sqrt_one_minus_abar * eps) / c.sqrt_abar",
      "x0 = (sample - c.sqrt_one_minus_abar * eps) * c.sqrt_abar",
      "epsilon -> x0 conversion multiplies by sqrt(abar)"),
    M("S13", "schedule.py",
      "beta_t = 1 - abar / abar_prev",
      "beta_t = 1 - abar",
      "DDPM beta of the (strided) step taken as 1 - abar_t"),
    M("S14", "schedule.py",
      "variance = ((1 - abar_prev) / (1 - abar) * beta_t).clamp(min=1e-20)",
      "variance = (1 - abar_prev) / (1 - abar) * beta_t",
      "clamp removed from the DDPM variance",
      equivalent="the variance is 0 only on the step from t = 0, whose noise the (t > 0) gate zeroes anyway; "
      "inactive slots (NaN either way) are discarded by torch.where"),
    M("S15", "schedule.py",
      "noise_std=variance.sqrt() * (t > 0).unsqueeze(-1),",
      "noise_std=variance.sqrt(),",
      "DDPM noise gate on the step from t = 0 removed",
      equivalent="on the step from t = 0 abar_prev = 1, the variance is 0 and clamped to 1e-20: without the "
      "gate the added noise is 1e-10 z, below float32 resolution of the actions"),
    M("S16", "schedule.py",
      "x0_coef=abar_prev.sqrt() * beta_t / (1 - abar),",
      "x0_coef=abar.sqrt() * beta_t / (1 - abar),",
      "DDPM posterior x0 coefficient uses abar_t instead of abar_prev"),
    M("S17", "schedule.py",
      "xt_coef=(1 - beta_t).sqrt() * (1 - abar_prev) / (1 - abar),",
      "xt_coef=(1 - beta_t) * (1 - abar_prev) / (1 - abar),",
      "DDPM posterior x_t coefficient without the square root"),
    M("S18", "schedule.py",
      "eps_coef=(1 - abar_prev).sqrt()",
      "eps_coef=(1 - abar).sqrt()",
      "DDIM direction term at the current level instead of the previous one"),
    M("S19", "schedule.py",
      "return torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)",
      "return torch.randn(x.shape, device=x.device, dtype=x.dtype)",
      "every draw ignores the generator (global RNG)"),
    M("S20", "schedule.py",
      "active=None if all_active else active,",
      "active=None,",
      "the inactive-slot mask always dropped: clean slots (k = 0) are stepped"),
    M("S21", "schedule.py",
      "active=None if all_active else active,",
      "active=active,",
      "the all-true mask kept while streaming (a wasted torch.where per step)"),
    # --- noise_schemes.py: chunk-wise bands ----------------------------------------------------------
    M("N01", "noise_schemes.py",
      "offset = torch.randint(1, s + 1, (batch_size, 1), device=device, generator=generator)",
      "offset = torch.randint(0, s, (batch_size, 1), device=device, generator=generator)",
      "chunk-wise band offset [0, s-1]: chunk 0 can be clean (t = -1)"),
    M("N02", "noise_schemes.py",
      "offset = torch.randint(1, s + 1, (batch_size, 1), device=device, generator=generator)",
      "offset = torch.randint(1, s + 1, (batch_size, geometry.horizon), device=device, generator=generator)",
      "chunk-wise offset drawn per slot, not shared by the sample"),
    M("N03", "noise_schemes.py",
      "k = geometry.slot_chunk_on(device).unsqueeze(0) * s + offset",
      "k = geometry.slot_chunk_on(device).unsqueeze(0) + offset",
      "chunk i's band shifted by i instead of i*s"),
    M("N04", "noise_schemes.py",
      "k = geometry.slot_chunk_on(device).unsqueeze(0) * s + offset",
      "k = geometry.start_levels.to(device).unsqueeze(0) - offset + 1",
      "band counted down from its top",
      equivalent="offset is uniform on 1..s, so (i+1)*s + 1 - offset has the same distribution as "
      "i*s + offset, still shared by all chunks of the sample"),
    M("N05", "noise_schemes.py",
      "bounds = list(itertools.accumulate(w[name] for name in active))",
      "bounds = list(itertools.accumulate(1.0 for name in active))",
      "mixture weights ignored (uniform over the active schemes)"),
    # --- unet.py: the step-embedding cache -----------------------------------------------------------
    M("U01", "unet.py",
      "return tuple((p.data_ptr(), p.dtype, p._version) for p in module.parameters())",
      "return tuple((p.data_ptr(), p.dtype) for p in module.parameters())",
      "cache key ignores in-place weight updates (stale embeddings after an optimiser step)"),
    M("U02", "unet.py",
      "return torch.get_autocast_dtype(device_type) if torch.is_autocast_enabled(device_type) else None",
      "return None",
      "cache key ignores autocast (a float32 embedding served under bfloat16 autocast)"),
    M("U03", "unet.py",
      "if stale or key != self._key:",
      "if not self._entries:",
      "a new plan (batch size, device) is never cached"),
    # --- inference delay: committed slots in the layout, the window, training, RTC, server, bench ---
    M("D01", "geometry.py",
      "source = torch.where(j >= self.n_past + d, j - d, j)",
      "source = j",
      "chunks not moved after the committed slots (their levels overlap the committed ones)"),
    M("D02", "geometry.py",
      "return (j >= self.n_past) & (j < self.n_past + d)",
      "return (j >= self.n_past) & (j <= self.n_past + d)",
      "one committed slot too many"),
    M("D03", "geometry.py",
      "return round_up(self.n_past + self.max_delay + self.n_future, self.downsampling)",
      "return round_up(self.n_past + self.n_future, self.downsampling)",
      "no room for the committed slots in the horizon"),
    M("D04", "buffer.py",
      "noise.steps)[:, committed:]",
      "noise.steps)",
      "the executed chunk taken where chunk 0 sits without delay (overlapping the committed actions)"),
    M("D05", "buffer.py",
      "self.last_chunk[:, tb - d - g.n_past : tb - d]",
      "self.last_chunk[:, tb - g.n_past :]",
      "past slots hold the last chunk's end instead of the action before the committed ones"),
    M("D06", "buffer.py",
      "chunks = self.sample[:, g.n_past : g.horizon - d]",
      "chunks = self.sample[:, g.n_past + d :]",
      "the buffer's chunks enter the window shifted by d (its first d slots dropped)"),
    M("D07", "buffer.py",
      "if generation != self._generation:  # its chunk would run in the episode that followed",
      "if False:",
      "a clear() during a call is undone when the call writes the buffer back"),
    M("D08", "buffer.py",
      "k_start = self.geometry.delayed(k_start.unsqueeze(0), delay, clean=0)[0]",
      "k_start = k_start",
      "the plan of a call with committed slots is the undelayed one (committed actions get denoised)"),
    M("D09", "noise_schemes.py",
      "return geometry.delayed(levels, delay, clean=CLEAN), geometry.committed_mask(delay)",
      "return levels, geometry.committed_mask(delay)",
      "training draws delays but noises the committed slots like any other"),
    M("D10", "noise_schemes.py",
      "geometry.max_delay + 1, (levels.shape[0],), device=levels.device, generator=generator",
      "geometry.max_delay, (levels.shape[0],), device=levels.device, generator=generator",
      "training never draws the largest delay"),
    M("D11", "modeling_sdp.py",
      "mask = None if committed is None else ~committed.unsqueeze(-1)",
      "mask = None",
      "the committed slots stay in the loss"),
    M("D12", "modeling_sdp.py",
      "committed = committed_under_rtc(len(rest)) if streaming and self.config.max_delay else 0",
      "committed = 0",
      "RTC: the leftover is not committed (the chunk is denoised as if it started at the observation)"),
    M("D17", "rtc.py",
      "    return n_left + 1",
      "    return n_left",
      "RTC: the action of the observation's own tick is not committed (the chunk is denoised a tick early)"),
    M("D19", "benchmarks/virtual_clock.py",
      "[q[-1]] * len(q) if self.frames_only else list(q)",
      "list(q)",
      "the delay bench's newest-frame history (the RTC engine's) is the full history"),
    M("D18", "rtc.py",
      "return torch.cat([following[:, :1], following], dim=1)",
      "return following",
      "RTC: the result is timed from the next action, not the observation's tick (the engine skips one)"),
    M("D13", "policy_server.py",
      "committed = left if self.policy.config.max_delay else 0",
      "committed = 0",
      "async server: the unexecuted rest is not committed"),
    M("D14", "benchmarks/virtual_clock.py",
      "self.queue = actions[ready - requested :]",
      "self.queue = actions",
      "naive async diffusion keeps the actions whose tick has passed"),
    M("D15", "benchmarks/virtual_clock.py",
      'committed = len(self.queue) if self.mode == "delay_aware" else 0',
      "committed = 0",
      "delay-aware bench rows run SDP without committed slots"),
    M("D16", "robots/pusht_sim.py",
      "while not self._over and len(self.rewards) < self._due(now):",
      "while False:",
      "pusht_sim waits for actions: a stall costs the robot nothing"),
    # --- data parallelism and mixed precision ---------------------------------------------------------
    M("R01", "data_parallel.py",
      "if size == 1:",
      "if size >= 1:",
      "every rank draws its training noise from the shared global stream"),
    M("R02", "data_parallel.py",
      "manual_seed(base * size + rank)",
      "manual_seed(base * size)",
      "every rank seeds its noise stream alike"),
    M("R03", "data_parallel.py",
      "if size == 1:",
      "if size == 0:",
      "one process draws from a stream of its own, no longer the global RNG (training changes)"),
    M("R04", "modeling_sdp.py",
      "eps = gaussian_like(trajectory, generator)",
      "eps = gaussian_like(trajectory)",
      "the training noise ignores the rank's stream"),
    M("R05", "noise_schemes.py",
      "u = torch.rand(batch_size, device=device, generator=generator)",
      "u = torch.rand(batch_size, device=device)",
      "the noise scheme of each sample ignores the rank's stream"),
    M("R06", "modeling_sdp.py",
      "return self.unet(sample, timesteps, global_cond=global_cond).to(sample.dtype)",
      "return self.unet(sample, timesteps, global_cond=global_cond)",
      "under autocast the schedule maths (x0, clipping) runs on the U-Net's bf16 output"),
    # --- modeling_sdp.py: the constant primer, the NaN guard -----------------------------------------
    M("P01", "modeling_sdp.py",
      "history[OBS_STATE][:, -1]",
      "history[OBS_STATE][:, 0]",
      "constant primer reads the oldest observation instead of the newest"),
    M("P02", "modeling_sdp.py",
      "scale, offset = state_to_action",
      "offset, scale = state_to_action",
      "constant primer's state -> action map with scale and offset swapped"),
    M("P03", "modeling_sdp.py",
      "refuse_non_finite(history, finite)  # the one host read, after the chunk is computed",
      "pass",
      "NaN guard dropped after the first chunk"),
    M("P04", "modeling_sdp.py",
      "self._queues = before\n",
      "\n",
      "a refused observation stays in the observation history"),
    # The async server's plan and history (policy_server.py): the buffer in step with the robot.
    M("A01", "policy_server.py",
      "if left > self.delay_ticks():",
      "if left > self.delay_ticks() + 1:",
      "streams a chunk one tick early (the chunk runs a tick later than its observation's delay)"),
    M("A02", "policy_server.py",
      "plan.actions[:, t - plan.start :]",
      "plan.actions[:, t - plan.start + 1 :]",
      "the resent plan skips the action at the observation's timestep (the reply is shifted by one)"),
    M("A03", "policy_server.py",
      "actions = chunk if rest is None else torch.cat([rest, chunk], dim=1)",
      "actions = chunk",
      "the unexecuted rest of the plan is not resent: the new chunk is timed from the observation"),
    M("A04", "policy_server.py",
      "if frame is not None else frames[0]",
      "if frame is not None else current",
      "a timestep never sent repeats the newest frame instead of the next newer one"),
    M("A05", "policy_server.py",
      "self._predicted_timesteps.discard(observation_t.get_timestep())",
      "pass",
      "a refused observation's timestep stays 'predicted': a corrected one at that timestep is skipped"),
    M("A06", "policy_server.py",
      "elif plan is not None and t >= plan.end:",
      "elif plan is not None and t > plan.end:",
      "a client past the plan's last action by one goes on streaming: its chunk runs a tick late"),
    # Deployment timing and state: restarts, retries, the delay estimate, resets, reconnects, sweeps.
    M("E01", "policy_server.py",
      "if plan is not None and (episode != plan.episode or t < plan.start):",
      "if plan is not None and t < plan.start:",
      "a restart without Ready at the plan's own start brings the old episode's plan back"),
    M("E02", "policy_server.py",
      "if observation_t.episode != self.episode:",
      "if False:",
      "an observation queued before the client started over is run in the new episode"),
    M("E03", "policy_server.py",
      "self.frames, self.last_processed_obs = {}, None\n                self.episode += 1\n",
      "self.frames, self.last_processed_obs = {}, None\n",
      "the server sees a restart without Ready but does not count it as a new episode"),
    M("E04", "policy_server.py",
      "must_go, self.retry = obs.must_go or self.retry, False",
      "must_go, self.retry = obs.must_go, False",
      "after a failed prediction the same state is dropped as too similar: the robot stalls for good"),
    M("E05", "policy_server.py",
      "self.error, self.retry = str(e), True",
      "self.error = str(e)",
      "a failed prediction does not let the retry through"),
    M("E06", "policy_server.py",
      "        if plan is not None:  # a stream's first chunk primes it (and may warm up): not its delay",
      "        if True:",
      "a stream's slow first chunk (priming, warm-up) sets the delay for the next eight"),
    M("E07", "policy_server.py",
      'self.streamed_from = getattr(self.current, "received", None)',
      "self.streamed_from = self.clock()",
      "the delay counts only what follows the chunk, not the queue, processors and denoising"),
    M("E08", "policy_server.py",
      "ticks = min(math.ceil(slowest * config.fps), policy_config.n_action_steps - 1)",
      "ticks = math.ceil(slowest * config.fps)",
      "one slow reply makes every observation stream a chunk: the robot runs chunks ahead"),
    M("E09", "policy_server.py",
      "if past_the_plan:",
      "if False:",
      "a stream restarted past the plan is timed from t: the client drops its first action"),
    M("E10", "buffer.py",
      "                raise StreamResetError(STREAM_RESET)\n            self.sample, self.last_chunk, "
      "self._past_noise = sample, None, None",
      "                pass\n            self.sample, self.last_chunk, self._past_noise = sample, None, None",
      "prime() ignores a reset since the call began: the stream is primed on the old episode"),
    M("E11", "modeling_sdp.py",
      "self._buffer.prime(primer, generator, generation)",
      "self._buffer.prime(primer, generator)",
      "the policy primes without the generation it read: a reset meanwhile is undone"),
    M("E12", "buffer.py",
      "its chunk would run in the episode that followed\n"
      "                raise StreamResetError(STREAM_RESET)",
      "its chunk would run in the episode that followed\n                return chunk",
      "a call that outlived a reset hands the old episode's chunk on (the RTC engine would queue it)"),
    M("E13", "rtc.py",
      "if rtc_config is not None and not rtc_config.enabled:",
      "if False:",
      "the RTC engine with rtc.enabled=false is served: the leftover runs twice"),
    M("E14", "robots/pusht_sim.py",
      "        self._start_episode()  # a reconnect is a new episode, not the end of the last one\n",
      "",
      "pusht_sim after a reconnect counts every action as after the episode's end"),
    M("E15", "policy_server.py",
      "    service.start_sweeping()\n",
      "",
      "the server never sweeps on its own: a vanished last client's policy stays in memory"),
    M("E16", "policy_server.py",
      "                    self.sweep()",
      "                    pass",
      "the sweeper thread runs but drops nothing"),
    M("E17", "benchmarks/deployment_schedules.py",
      "if self.stream_started.get(stream, -1.0) < self.episode_start:",
      "if False:",
      "the schedule driver lets a robot run another episode's actions"),
    M("E18", "benchmarks/deployment_schedules.py",
      "elif pos != expected:",
      "elif False:",
      "the schedule driver lets a robot repeat or skip actions"),
    # The policy server under faults (policy_server.py, protocol_pickle.py).
    M("F01", "policy_server.py",
      "problem = raw_observation_problem(obs.get_observation(), self.lerobot_features)",
      "self.frames[t] = obs\n        problem = raw_observation_problem("
      "obs.get_observation(), self.lerobot_features)",
      "a refused observation is stored first and poisons the next histories"),
    M("F02", "policy_server.py",
      "if key in CLIENT_ID_KEYS and value:",
      "if False:",
      "the client-id metadata is ignored: a reconnect from a new port loses its session"),
    M("F03", "policy_server.py",
      "    timer.start()\n",
      "\n",
      "a stalled upload holds its worker thread until the client lets go"),
    M("F04", "policy_server.py",
      "elif session.in_flight >= self.config.max_calls_per_client:",
      "elif False:",
      "one client may hold any number of calls (and every worker thread)"),
    M("F05", "policy_server.py",
      "message = protocol_pickle.loads(data)",
      "message = pickle.loads(data)",
      "client bytes are unpickled unrestricted: a payload runs code on the server"),
    M("F06", "policy_server.py",
      "self.sessions.pop(gone).stop()",
      "self.sessions[gone].stop()",
      "an idle session is stopped but kept: its slot and its policy are never freed"),
    M("F07", "policy_server.py",
      "self.frames, self.last_processed_obs = {}, None",
      "self.frames = {}",
      "a restart without Ready keeps LeRobot's last processed frame: the new episode's first one is skipped"),
    M("F08", "policy_server.py",
      "kept = () if restart else self._predicted_timesteps",
      "kept = self._predicted_timesteps",
      "a restart keeps the old episode's predicted timesteps"),
    M("Q01", "protocol_pickle.py",
      '("torch.storage", "_load_from_bytes"): _load_storage,',
      '("torch.storage", "_load_from_bytes"): None,',
      "a tensor storage is read with torch's unrestricted unpickler: code hidden in it runs"),
    M("Q02", "protocol_pickle.py",
      "if (module, name) not in _ADMITTED:",
      "if False:",
      "every global is admitted: plain pickle"),
    # Warm start from a Diffusion Policy (warm_start.py).
    M("W01", "warm_start.py",
      "    _check_normalization(dp, config, source)\n",
      "",
      "a DP that normalises actions another way is copied without a word"),
    # The model card under LeRobot's main branch (model_card.py).
    M("A07", "policy_server.py",
      "if not s.in_flight and now - s.last_seen > idle",
      "if now - s.last_seen > idle",
      "a session busy in a call longer than the timeout is dropped as idle"),
    M("C01", "model_card.py",
      'title = f"# Model Card for {POLICY_TYPE}\\n"',
      'title = "# Model Card for "',
      "every policy's card (not only SDP's) gets the SDP introduction"),
    M("C02", "model_card.py",
      "module.generate_model_card = generate_model_card  # callers look it up in the module when they run",
      "pass",
      "the free function is never wrapped: SDP cards lose their introduction on LeRobot main"),
    # SDP's bookkeeping against its own U-Net timed alone (benchmarks/compiled.py).
    M("K01", "benchmarks/compiled.py",
      "        sample = unet(sample, t, global_cond=global_cond)",
      "        unet(sample, t, global_cond=global_cond)",
      "the U-Net calls are not chained: compilation may drop all but the last"),
    M("K02", "benchmarks/compiled.py",
      "run()  # compiles",
      "pass",
      "no warm-up chunk: compilation is timed as if it were a call"),
    M("K03", "benchmarks/compiled.py",
      "model.unet = StandInUnet(",
      "model.unet = unet or StandInUnet(",
      "the real U-Net keeps running while the bookkeeping is timed"),
    M("K04", "benchmarks/compiled.py",
      "        model.unet = unet\n",
      "\n",
      "the stand-in stays in the policy after the bookkeeping is timed"),
    # --- memory_dataset.py: windows served from memory, LeRobot's indices and padding -----------------
    M("I01", "memory_dataset.py",
      "padding[f\"{key}_is_pad\"] = (wanted < start) | (wanted >= end)",
      "padding[f\"{key}_is_pad\"] = (wanted < start) | (wanted > end)",
      "the first frame past an episode's end not marked as padding"),
    M("I02", "memory_dataset.py",
      "rows = wanted.clamp(start, end - 1)",
      "rows = wanted.clamp(0, len(self.columns[\"index\"]) - 1)",
      "windows read across episode boundaries instead of repeating the edge frame"),
    M("I03", "memory_dataset.py",
      "batch[key] = self.columns[key][rows if self.row_of is None else self.row_of[rows]]",
      "batch[key] = self.columns[key][rows]",
      "a subset of episodes read at absolute frame indices instead of its own rows"),
    M("I04", "memory_dataset.py",
      "        batch.update(padding)\n",
      "\n",
      "padding masks left out of the sample"),
    M("I05", "memory_dataset.py",
      "if meta.camera_keys:",
      "if False:",
      "a dataset with cameras served from memory without its images"),
    M("I06", "memory_dataset.py",
      "tasks = [self.task_names[t] for t in batch[\"task_index\"].tolist()]",
      "tasks = [self.task_names[0]] * len(idx)",
      "every sample of a batch given the first task's string"),
    M("I07", "memory_dataset.py",
      "    LeRobotDataset.__getitems__ = get_items\n",
      "\n",
      "the DataLoader reads a batch sample by sample instead of in one gather"),
    M("I08", "memory_dataset.py",
      "return [dataset[i] for i in indices] if table is None else table.items(indices)",
      "return [dataset[i] for i in indices] if table is None else table.items(sorted(indices))",
      "a batch's samples returned in another order than the sampler's"),
    # The diagnostic samplers of `--policy.sampling` (modeling_sdp.py).
    M("M01", "modeling_sdp.py",
      'if self._buffer.batch_size not in (None, batch_size) or sampling == "fresh":',
      "if self._buffer.batch_size not in (None, batch_size):",
      "sampling=fresh keeps the last chunk's buffer (it streams)"),
    M("M02", "modeling_sdp.py",
      'kind = "denoise" if sampling == "fresh" else None',
      "kind = None",
      "sampling=fresh primes with action_primer instead of a full denoise from its own observation"),
    M("M03", "modeling_sdp.py",
      "return actions[:, self.geometry.executed]",
      "return actions[:, : self.config.n_action_steps]",
      "sampling=full_denoise returns the past slot and the chunk shifted one slot early"),
    M("M04", "modeling_sdp.py",
      'if sampling == "full_denoise":',
      'if sampling == "full_denoise" and False:',
      "sampling=full_denoise streams instead"),
    M("M05", "modeling_sdp.py",
      "            refuse_non_finite(history, finite_flags(history))\n",
      "\n",
      "sampling=full_denoise samples from a NaN observation"),
    M("M06", "modeling_sdp.py",
      'if sampling != "stream" and committed:',
      "if False:",
      "the diagnostic samplers silently ignore committed actions"),
    M("M07", "modeling_sdp.py",
      "primer = kind or self.config.action_primer",
      "primer = self.config.action_primer",
      "the primer override is ignored"),
    # One rollout video as a small animation (benchmarks/animation.py).
    M("V01", "benchmarks/animation.py",
      "if len(data) <= max_bytes:",
      "if True:",
      "the size limit is ignored"),
    M("V02", "benchmarks/animation.py",
      "kept = frames[::every]",
      "kept = frames",
      "every frame is kept whatever --every says"),
    M("V03", "benchmarks/animation.py",
      "if args.output.exists() and not args.overwrite:",
      "if False:",
      "an existing file is overwritten without --overwrite"),
    M("V04", "benchmarks/animation.py",
      "duration=round(1000 / fps),",
      "duration=100,",
      "the animation ignores the video's frame rate"),
    # --- training recipes: the whole-table chunk-wise draw, the curriculum, Min-SNR, the screen -------
    M("T01", "noise_schemes.py",
      "return geometry.slot_chunk_on(device).unsqueeze(0) * band + offset - 1",
      "return geometry.slot_chunk_on(device).unsqueeze(0) * band + offset",
      "whole-table chunk-wise levels one timestep too high (t = T reachable)"),
    M("T02", "noise_schemes.py",
      "offset = torch.randint(1, band + 1, (batch_size, 1), device=device, generator=generator)",
      "offset = torch.randint(1, band, (batch_size, 1), device=device, generator=generator)",
      "the whole-table draw never reaches its top staircase"),
    M("T03", "noise_schemes.py",
      "band = schedule.num_train_timesteps // geometry.n_chunks",
      "band = geometry.steps_per_call",
      "the whole-table draw's bands as wide as the sampler's"),
    M("T04", "noise_schemes.py",
      'draws = SCHEMES | {"chunkwise": CHUNKWISE_GRIDS[chunkwise_grid]}',
      "draws = SCHEMES",
      "chunkwise_grid ignored: always the sampler's grid"),
    M("T05", "noise_schemes.py",
      "return (step < self.constant_steps).float()",
      "return (step <= self.constant_steps).float()",
      "the curriculum switches one step late"),
    M("T06", "noise_schemes.py",
      "return (1.0 - (step - self.constant_steps).float() / self.ramp_steps).clamp(0.0, 1.0)",
      "return (1.0 - step.float() / self.ramp_steps).clamp(0.0, 1.0)",
      "the ramp starts at step 0, not after the constant steps"),
    M("T07", "noise_schemes.py",
      "take = torch.rand(batch_size, device=device, generator=generator) < constant_share",
      "take = torch.rand(batch_size, device=device, generator=generator) > constant_share",
      "the curriculum's share inverted: the mixture first, constant levels after"),
    M("T08", "noise_schemes.py",
      "return self.constant_steps + self.ramp_steps > 0",
      "return self.constant_steps > 0",
      "a ramp-only curriculum is switched off"),
    M("T09", "modeling_sdp.py",
      "return self.model.compute_loss(batch, self._training_generator(), self.ema_step), None",
      "return self.model.compute_loss(batch, self._training_generator(), self.ema_step * 0), None",
      "the loss never sees the step: the curriculum stays at step 0"),
    M("T10", "modeling_sdp.py",
      "self.ema_step += 1  # on the device: no host read per training step",
      "self.ema_step += int(self.ema_model is not None)  # on the device: no host read per training step",
      "the step counts only with EMA: without it a curriculum never leaves step 0"),
    M("T11", "modeling_sdp.py",
      "share = curriculum.constant_share(step) if curriculum.enabled else None",
      "share = None",
      "noise_curriculum ignored"),
    M("T12", "modeling_sdp.py",
      "loss = loss * min_snr_weights(self.schedule, levels, cfg.min_snr_gamma, cfg.prediction_type)",
      "loss = loss * 1.0",
      "min_snr_gamma ignored"),
    M("T13", "loss_weighting.py",
      "snr = abar / (1 - abar)",
      "snr = (1 - abar) / abar",
      "SNR inverted"),
    M("T14", "loss_weighting.py",
      "return gamma / snr.clamp(min=gamma)",
      "return gamma / snr",
      "epsilon weights gamma / SNR unclipped: the noisiest slots weigh more than 1"),
    M("T15", "loss_weighting.py",
      "return snr.clamp(max=gamma)",
      "return snr.clamp(min=gamma)",
      "sample prediction weighted by max(SNR, gamma)"),
    M("T16", "configuration_sdp.py",
      'if self.chunkwise_grid == "training_table" and self.num_train_timesteps % self.n_chunks:',
      'if self.chunkwise_grid == "training_table" and self.num_train_timesteps % 1:',
      "uneven whole-table bands accepted"),
    M("T17", "configuration_sdp.py",
      "if self.min_snr_gamma is not None and not self.min_snr_gamma > 0:",
      "if self.min_snr_gamma is not None and self.min_snr_gamma < 0:",
      "min_snr_gamma = 0 accepted (every weight 0)"),
    M("T18", "benchmarks/quality.py",
      '"screen_min_snr5": [*base, "--policy.min_snr_gamma=5.0"],',
      '"screen_min_snr5": base,',
      "the Min-SNR screen trains the default recipe"),
    M("T19", "benchmarks/quality.py",
      'f"--policy.noise_curriculum.ramp_steps={max(1, steps // 2)}"',
      'f"--policy.noise_curriculum.constant_steps={max(1, steps // 2)}"',
      "the ramp screen switches instead"),
    # --- probe: true against shuffled observations ---------------------------------------------------
    M("T20", "benchmarks/quality.py",
      "kept = [a for a in run.policy_args if not any(a.startswith(k) for k in keys)]",
      "kept = list(run.policy_args)",
      "a carried recipe flag lands beside the run's own value of the key"),
    M("T21", "benchmarks/quality.py",
      "if not flags or \"--policy.type=sdp\" not in run.policy_args:",
      "if not flags:",
      "DP's runs get SDP's recipe flags"),
    M("T22", "noise_schemes.py",
      "schedule.num_train_timesteps, (batch_size, geometry.n_chunks), device=device, generator=generator",
      "schedule.num_train_timesteps, (batch_size, 1), device=device, generator=generator",
      "independent chunks share one level (constant levels)"),
    M("T23", "noise_schemes.py",
      "return per_chunk[:, geometry.slot_chunk_on(device)]",
      "return per_chunk.sort(dim=1).values[:, geometry.slot_chunk_on(device)]",
      "independent chunks sorted into a staircase: the later chunk never the cleaner"),
    M("T24", "noise_schemes.py",
      '"independent_chunks": independent_chunk_levels,',
      '"independent_chunks": independent_levels,',
      "the independent_chunks weight draws one level per slot"),
    M("T25", "benchmarks/quality.py",
      '{"constant": 0.2, "chunkwise": 0.6, "independent_chunks": 0.2}',
      '{"constant": 0.2, "chunkwise": 0.6, "independent": 0.2}',
      "the probe's candidate screens per-slot levels instead of per-chunk ones"),
    M("O01", "benchmarks/probe.py",
      'conds["shuffled"] = conds["true"].roll(1, dims=0)',
      'conds["shuffled"] = conds["true"]',
      "the shuffled conditioning is the true one"),
    M("O02", "benchmarks/probe.py",
      "bands = (patterns * probe.bands) // schedule.num_train_timesteps  # (P, T)",
      "bands = (patterns * probe.bands) // (schedule.num_train_timesteps + 1)  # (P, T)",
      "band edges off"),
    M("O03", "benchmarks/probe.py",
      "cell = chunks.unsqueeze(0) * probe.bands + bands  # (P, T): the (chunk, band) of every slot",
      "cell = chunks.unsqueeze(0) + bands  # (P, T): the (chunk, band) of every slot",
      "chunks and bands share cells"),
    M("O04", "benchmarks/probe.py",
      "out = (x_t - abar.sqrt() * out) / (1 - abar).sqrt()",
      "out = out",
      "a sample-predicting network scored on its x0, not its epsilon"),
    M("O05", "benchmarks/probe.py",
      "return (j - n_past).clamp(min=0) // chunk_len",
      "return j // chunk_len",
      "DP's past slots not counted in chunk 0"),
    M("O06", "benchmarks/probe.py",
      "return [frames[round(j * (len(frames) - 1) / (max_windows - 1))] for j in range(max_windows)]",
      "return frames[:max_windows]",
      "windows taken from the first episodes only"),
    M("O07", "benchmarks/probe.py",
      "eps = torch.randn(actions.shape, generator=generator, device=device)",
      "eps = torch.randn(actions.shape, device=device)",
      "the probe's noise unseeded: a rerun differs"),
    M("O08", "benchmarks/probe.py",
      "0, cell[p], torch.full_like(cell[p], size * actions.shape[-1], dtype=count.dtype)",
      "0, cell[p], torch.full_like(cell[p], size, dtype=count.dtype)",
      "the losses divided by windows, not by values"),
    # --- training speed: thread count, fused Adam, one-pass EMA, the train-profile and its limit -------
    M("O09", "benchmarks/probe.py",
      'return policy._sampling_model() if policy.config.type == "sdp" else policy.diffusion',
      'return policy.model if policy.config.type == "sdp" else policy.diffusion',
      "an SDP policy with EMA is probed on its raw weights, not the averaged ones it samples with"),
    M("T26", "benchmarks/quality.py",
      'count = "" if n == budget.n_episodes else f"_{n}episodes"',
      'count = ""',
      "an evaluation of another episode count reuses the folder, and the results, of the budget's"),
    M("T27", "benchmarks/quality.py",
      "n = budget.n_episodes if args.n_episodes is None else args.n_episodes",
      "n = budget.n_episodes",
      "--n_episodes is ignored"),
    M("T28", "configuration_sdp.py",
      "    min_snr_gamma: float | None = 5.0\n",
      "    min_snr_gamma: float | None = None\n",
      "the default recipe falls back to the paper's unweighted loss"),
    M("H01", "lerobot_cli.py",
      "return max(1, len(os.sched_getaffinity(0)) // concurrent)",
      "return 1",
      "a run without DataLoader workers still trains on one thread"),
    M("H02", "lerobot_cli.py",
      "    if key in flags:\n        return flags[key]\n",
      "\n",
      "the command line's --num_workers ignored"),
    M("H03", "configuration_sdp.py",
      "adam = FusedAdamConfig if self.optimizer_fused else AdamConfig",
      "adam = AdamConfig",
      "the optimizer preset never fused"),
    M("H04", "ema.py",
      "weight = (1.0 - decay).to(avg[0].dtype)",
      "weight = decay.to(avg[0].dtype)",
      "EMA moves by decay instead of 1 - decay"),
    M("H05", "benchmarks/train_profile.py",
      "    torch.set_num_threads(c.variant.threads)\n",
      "\n",
      "every contender runs on whatever thread count the last one set"),
    M("H06", "benchmarks/train_profile.py",
      "torch.manual_seed(cfg.seed or 0)  # every contender of a config starts from the same weights",
      "pass",
      "contenders start from different weights"),
    M("H07", "benchmarks/hardware_limit.py",
      "return 2 * self.batch * self.channels * self.length * self.channels * self.kernel",
      "return self.batch * self.channels * self.length * self.channels * self.kernel",
      "conv FLOPs counted as multiply-adds, not FLOPs"),
    M("H08", "benchmarks/train_profile.py",
      "bins.append((values.mean().item(), (values.std() / math.sqrt(size)).item()))",
      "bins.append((values.mean().item(), values.std().item()))",
      "a bin's spread reported as its standard deviation, not its standard error"),
    M("H09", "lerobot_cli.py",
      "return max(1, len(os.sched_getaffinity(0)) // concurrent)",
      "return len(os.sched_getaffinity(0))",
      "trainings that run at once each start a thread per core"),
    M("H10", "lerobot_cli.py",
      "count = exported[0] if exported else str(threads)",
      "count = str(threads)",
      "an exported OMP_NUM_THREADS leaves MKL's pool at the default count"),
    M("H11", "benchmarks/quality.py",
      "        concurrent=plan.jobs,\n",
      "\n",
      "quality --jobs N trains each run as if it were alone"),
    # --- training precision: bf16 autocast where the CPU computes bf16 natively ---------------------
    M("H12", "lerobot_cli.py",
      "if command_setting(train_args, \"policy.use_amp\") is not None:",
      "if False:",
      "the user's or the config's use_amp overridden by the automatic choice"),
    M("H13", "lerobot_cli.py",
      "if command_setting(train_args, \"policy.device\") != \"cpu\":",
      "if False:",
      "bf16 autocast forced on a training on a GPU (fp16 there) because the CPU has native bf16"),
    M("H14", "lerobot_cli.py",
      "return next((flag for flag in NATIVE_BF16_FLAGS if flag in present), None)",
      "return next((flag for flag in NATIVE_BF16_FLAGS if any(flag in p for p in present)), None)",
      "a CPU flag that merely contains avx512_bf16 taken for native bf16"),
    M("H15", "lerobot_cli.py",
      "cmd = [*train_command(processes), *args, *amp, f\"--steps={steps}\", f\"--output_dir={train_dir}\"]",
      "cmd = [*train_command(processes), *args, f\"--steps={steps}\", f\"--output_dir={train_dir}\"]",
      "the chosen precision never reaches lerobot-train"),
    M("H16", "benchmarks/quality.py",
      "        precision=plan.precision,\n",
      "\n",
      "quality --precision ignored"),
    M("H17", "robomimic/job.py",
      "precision=\"fp32\")",
      "precision=\"auto\")",
      "the robomimic job trains in bf16 by default, unmeasured against fp32's quality"),
]  # fmt: skip


@dataclass
class Result:
    id: str
    file: str
    description: str
    equivalent: str | None
    status: str  # killed | survived | error
    killed_by: str
    seconds: float


def check_list(mutants: list[Mutant], root: Path) -> list[str]:
    """Every original text occurs exactly once in its file: the list cannot silently rot."""
    problems, seen = [], set()
    for m in mutants:
        if m.id in seen:
            problems.append(f"{m.id}: duplicate id")
        seen.add(m.id)
        path = root / PKG / m.file
        if not path.is_file():
            problems.append(f"{m.id}: {PKG}/{m.file} does not exist")
            continue
        count = path.read_text().count(m.original)
        if count != 1:
            where = "not found" if count == 0 else f"found {count} times (ambiguous)"
            problems.append(f"{m.id}: original text {where} in {PKG}/{m.file}: {m.original!r}")
        if m.original == m.replacement:
            problems.append(f"{m.id}: replacement equals the original")
    return problems


def make_copy(dest: Path) -> Path:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".pytest_cache")
    for name in COPIED:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore)
        else:
            shutil.copy2(src, dest / name)
    return dest


def test_env(root: Path) -> dict:
    env = dict(os.environ)
    env.update(
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        # a same-size mutant written within the same second must not load a stale .pyc
        PYTHONDONTWRITEBYTECODE="1",
        PYTHONPATH=str(root),  # the copy, ahead of the editable install of the working tree
        HF_HUB_OFFLINE="1",
        WANDB_MODE="disabled",
    )
    return env


def run_tests(root: Path, tests: list[str], deselect: list[str], timeout: float) -> tuple[int, str]:
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    for node in deselect:
        cmd += ["--deselect", node]
    try:
        proc = subprocess.run(
            cmd, cwd=root, env=test_env(root), capture_output=True, text=True, timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        return -1, out + f"\n[timeout after {timeout:.0f} s]"
    return proc.returncode, proc.stdout + proc.stderr


def first_failure(rc: int, output: str) -> str:
    for line in output.splitlines():
        if line.startswith(("FAILED ", "ERROR ")):
            return line.split(" - ")[0].split(" ", 1)[1]
    if "[timeout" in output:
        return "timeout"
    # No test failed: pytest itself died (a signal, a crash in a library thread); say so, with the
    # last line it left, so that a flaky kill is not mistaken for a test that noticed the mutant.
    tail = [line for line in output.splitlines() if line.strip()]
    return f"pytest exit {rc}, no failed test: " + (tail[-1][:100] if tail else "no output")


def run_mutant(m: Mutant, root: Path, tests, deselect, timeout) -> Result:
    path = root / PKG / m.file
    original = path.read_text()
    start = time.monotonic()
    try:
        path.write_text(original.replace(m.original, m.replacement, 1))
        rc, output = run_tests(root, tests, deselect, timeout)
    finally:
        path.write_text(original)
    if rc == 0:
        status, by = "survived", ""
    elif rc == 5:  # no tests collected: the harness is broken, not the mutant
        status, by = "error", "pytest collected no tests"
    else:
        status, by = "killed", first_failure(rc, output)
    return Result(m.id, m.file, m.description, m.equivalent, status, by, round(time.monotonic() - start, 1))


def verdict(r: Result) -> str:
    if r.status == "error":
        return "ERROR"
    if r.equivalent:
        return "ok (equivalent, survives)" if r.status == "survived" else "EQUIVALENCE CLAIM WRONG (killed)"
    return "ok" if r.status == "killed" else "SURVIVED"


def write_reports(results: list[Result], out: Path, meta: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps({**meta, "mutants": [asdict(r) for r in results]}, indent=2))
    lines = [
        "# Mutation check of the streaming core",
        "",
        f"`{meta['command']}` at {meta['commit']}{' (dirty tree)' if meta['dirty'] else ''}, "
        f"{meta['finished']}, {meta['wall_s']:.0f} s wall.",
        f"Tests: {' '.join(meta['tests'])}"
        + (f"; deselected: {meta['deselect']}" if meta["deselect"] else ""),
        "",
        f"**{meta['summary']}**",
        "",
        "| id | file | mutation | result | killed by | s |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        what = r.description + (f" *(equivalent: {r.equivalent})*" if r.equivalent else "")
        lines.append(f"| {r.id} | {r.file} | {what} | {verdict(r)} | {r.killed_by} | {r.seconds} |")
    (out / "report.md").write_text("\n".join(lines) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--only", default="", help="comma-separated mutant ids")
    parser.add_argument("--list", action="store_true", help="check the list against the sources and print it")
    parser.add_argument("--skip-equivalent", action="store_true", help="do not run the equivalent mutants")
    parser.add_argument("--out", type=Path, default=REPO / "outputs" / "mutants")
    parser.add_argument("--jobs", type=int, default=1, help="mutants run in parallel (one copy each)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds per mutant's test run")
    parser.add_argument(
        "--deselect", action="append", default=[], help="pytest node id to leave out (recorded in the report)"
    )
    parser.add_argument(
        "--tests", nargs="+", default=CORE_TESTS, help="test paths to run instead of the core tests (quick)"
    )
    args = parser.parse_args()

    problems = check_list(MUTANTS, REPO)
    if problems:
        print("error: the mutant list no longer matches the sources; update .ci/mutants.py:", file=sys.stderr)
        for p in problems:
            print(f"  {p}", file=sys.stderr)
        return 2
    mutants = MUTANTS
    if args.only:
        wanted = {i.strip() for i in args.only.split(",") if i.strip()}
        unknown = wanted - {m.id for m in MUTANTS}
        if unknown:
            print(f"error: unknown mutant ids {sorted(unknown)}", file=sys.stderr)
            return 2
        mutants = [m for m in MUTANTS if m.id in wanted]
    if args.skip_equivalent:
        mutants = [m for m in mutants if not m.equivalent]
    if args.list:
        for m in mutants:
            print(f"{m.id}  {m.file:<16} {m.description}" + ("  [equivalent]" if m.equivalent else ""))
        return 0

    started, t0 = time.strftime("%Y-%m-%d %H:%M:%S"), time.monotonic()
    tmp = Path(tempfile.mkdtemp(prefix="sdp-mutants-"))
    try:
        copies = [make_copy(tmp / f"copy{i}") for i in range(max(1, args.jobs))]
        probe = subprocess.run(
            [sys.executable, "-c", f"import {PKG}; print({PKG}.__file__)"],
            cwd=copies[0], env=test_env(copies[0]), capture_output=True, text=True, check=False,
        )  # fmt: skip
        if not probe.stdout.strip().startswith(str(copies[0])):
            print(
                f"error: the copy does not import its own {PKG}: {probe.stdout}{probe.stderr}",
                file=sys.stderr,
            )
            return 2
        print(f"{len(mutants)} mutants, tests: {' '.join(args.tests)}")
        print("baseline (unmutated copy) ...", flush=True)
        rc, output = run_tests(copies[0], args.tests, args.deselect, args.timeout)
        if rc != 0:
            print(output[-4000:], file=sys.stderr)
            print(
                "error: the unmutated code fails the core tests; fix them first "
                "(or --deselect a test that is known to fail for an unrelated reason).",
                file=sys.stderr,
            )
            return 2
        print(f"baseline passes ({time.monotonic() - t0:.0f} s)", flush=True)

        pool: queue.Queue[Path] = queue.Queue()
        for c in copies:
            pool.put(c)

        def job(m: Mutant) -> Result:
            root = pool.get()
            try:
                r = run_mutant(m, root, args.tests, args.deselect, args.timeout)
            finally:
                pool.put(root)
            print(f"{r.id:<4} {verdict(r):<34} {r.seconds:6.1f} s  {r.description}", flush=True)
            return r

        with ThreadPoolExecutor(max_workers=len(copies)) as ex:
            results = list(ex.map(job, mutants))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    wall = time.monotonic() - t0
    bad = [r for r in results if verdict(r) not in ("ok", "ok (equivalent, survives)")]
    behavioural = [r for r in results if not r.equivalent]
    killed = sum(r.status == "killed" for r in behavioural)
    summary = (
        f"{killed}/{len(behavioural)} behaviour-changing mutants killed, "
        f"{sum(r.status == 'survived' for r in results if r.equivalent)}/{len(results) - len(behavioural)} "
        f"equivalent mutants survive; {len(bad)} problem(s)"
    )
    git = lambda *a: subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()  # noqa: E731
    meta = dict(
        command="python .ci/mutants.py " + " ".join(sys.argv[1:]),
        commit=git("rev-parse", "--short", "HEAD"),
        dirty=bool(git("status", "--porcelain", "--", PKG, "tests")),
        started=started,
        finished=time.strftime("%Y-%m-%d %H:%M:%S"),
        wall_s=round(wall, 1),
        tests=args.tests,
        deselect=args.deselect,
        summary=summary,
    )
    write_reports(results, args.out, meta)

    print()
    print(f"{'id':<4} {'file':<16} {'result':<34} {'killed by':<70}")
    for r in results:
        print(f"{r.id:<4} {r.file:<16} {verdict(r):<34} {r.killed_by[:70]}")
    print(f"\n{summary}; {wall:.0f} s. Reports: {args.out / 'report.md'}, {args.out / 'report.json'}")
    for r in bad:
        print(f"  PROBLEM {r.id}: {verdict(r)}: {r.description}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
