"""The latency benchmark end to end on a tiny CPU run, through the `lerobot-sdp-bench` entry point:
the JSON's fields, counted denoiser calls and sane (not timed) values; and the fairness of the
comparison (DP gets SDP's denoiser and horizon)."""

import json
import math

import pytest
import torch

from lerobot_sdp import chunk_cost
from lerobot_sdp.benchmarks import cli, latency, latency_measure

SAMPLERS = {"DDIM4": 4, "DDPM6": 6}
N_CHUNKS = [1, 2, 4]
BATCH_SIZES = [1, 3]


def run_bench(tmp_path, *extra: str) -> dict:
    threads = torch.get_num_threads()
    torch.set_num_threads(3)  # not the run's 1 (the suite itself may run on one thread)
    try:
        # One thread: on a loaded CI machine two OpenMP threads can be several times slower.
        argv = ["latency", "--quick", "--device", "cpu", "--steps", "2", "--num_threads", "1"]
        cli.main([*argv, "--output_dir", str(tmp_path), *extra])
        assert torch.get_num_threads() == 3  # an in-process run leaves the caller's setting alone
    finally:
        torch.set_num_threads(threads)
    return json.loads((tmp_path / "latency.json").read_text())


def check_timings(stats: dict) -> None:
    for key in ("chunk_latency_ms", "per_action_ms", "denoiser_call_ms"):
        assert stats[key]["p50"] > 0, key
        assert stats[key]["p95"] >= stats[key]["p50"], key
        assert stats[key]["n"] == 2, key
    assert stats["image_encoder_ms"]["p50"] == 0  # state observations: no camera encoder
    assert math.isfinite(stats["bookkeeping_fraction_of_denoiser_call"]["p50"])
    assert stats["primer"]["latency_ms"] > 0


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("latency")
    batch_sizes = [str(b) for b in BATCH_SIZES]
    n_chunks = [str(h) for h in N_CHUNKS]
    result = run_bench(out, "--samplers", *SAMPLERS, "--n_chunks", *n_chunks, "--batch_sizes", *batch_sizes)
    assert (out / "latency_h_sweep.png").stat().st_size > 0
    return result


def test_environment_and_settings(report):
    env = report["environment"]
    for key in ("python", "torch", "lerobot", "diffusers", "cpu_model", "cpu_count", "torch_num_threads"):
        assert env[key], key
    settings = report["settings"]
    assert settings["samplers"] == list(SAMPLERS)
    assert settings["n_chunks"] == N_CHUNKS
    assert "random" in settings["weights"]


def test_every_case_is_measured_or_skipped_with_a_reason(report):
    results = report["results"]
    assert len(results) == len(BATCH_SIZES) * len(SAMPLERS) * len(N_CHUNKS)
    skipped = [(r["sampler"], r["n_chunks"]) for r in results if "skipped" in r]
    assert sorted(set(skipped)) == [("DDPM6", 4)]  # 6 % 4 != 0
    assert len(skipped) == len(BATCH_SIZES)


def test_counted_denoiser_calls_and_sane_values(report):
    for r in report["results"]:
        if "skipped" in r:
            continue
        n, h = SAMPLERS[r["sampler"]], r["n_chunks"]
        assert r["num_inference_steps"] == n
        assert r["sdp"]["denoiser_calls_per_chunk"] == n // h
        assert r["dp"]["denoiser_calls_per_chunk"] == n
        # zero primer: the first call costs one ordinary chunk; DP's first call is an ordinary chunk.
        assert r["sdp"]["primer"]["denoiser_calls"] == n // h
        assert r["dp"]["primer"]["denoiser_calls"] == n
        check_timings(r["sdp"])
        check_timings(r["dp"])
        assert r["ratio"]["target"] == pytest.approx(1.1 / h)
        assert r["ratio"]["sdp_over_dp_chunk_p50"] > 0
        assert isinstance(r["ratio"]["meets_target"], bool)


def test_denoise_primer_is_reported_apart(tmp_path):
    report = run_bench(tmp_path, "--samplers", "DDIM4", "--n_chunks", "2", "--action_primer", "denoise")
    (case,) = report["results"]
    assert case["sdp"]["primer"]["denoiser_calls"] == 4 + 2  # full denoise, then one streaming step
    assert case["sdp"]["denoiser_calls_per_chunk"] == 2


def test_an_existing_report_is_kept_without_overwrite(tmp_path):
    (tmp_path / "latency.json").write_text("{}")
    with pytest.raises(SystemExit, match="pass --overwrite"):
        run_bench(tmp_path, "--samplers", "DDIM4", "--n_chunks", "1")
    assert (tmp_path / "latency.json").read_text() == "{}"
    assert run_bench(tmp_path, "--samplers", "DDIM4", "--n_chunks", "1", "--overwrite")["results"]


def test_dp_gets_the_same_denoiser_and_horizon_as_sdp():
    args = cli.build_parser().parse_args(["latency", "--quick"])
    latency.resolve_defaults(args)
    sdp, dp = latency_measure.build_policies(
        args, latency_measure.Case("cpu", 1, latency_measure.Sampler("DDIM", 4), 2)
    )
    assert dp.config.horizon == sdp.config.horizon == 20  # 1 past + 2 chunks x 8 + 3 padding
    for name in (
        "down_dims",
        "kernel_size",
        "diffusion_step_embed_dim",
        "noise_scheduler_type",
        "crop_shape",
    ):
        assert getattr(dp.config, name) == getattr(sdp.config, name), name
    assert dp.config.num_inference_steps == sdp.config.num_inference_steps == 4

    def unet_shapes(policy):
        (unet, *_) = chunk_cost.denoisers(policy)
        return {
            k: v.shape for k, v in unet.state_dict().items() if not k.startswith("diffusion_step_encoder")
        }

    assert unet_shapes(sdp) == unet_shapes(dp)  # only the step encoder differs (per-slot levels)
