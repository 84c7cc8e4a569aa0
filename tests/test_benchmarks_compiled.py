"""`lerobot-sdp-bench compiled` end to end on its CI-sized run: four policies timed, SDP's compiled
actions equal its eager ones, the floor derived from the measured bandwidth (values sane, not timed)."""

import json

import pytest
import torch
from sdp_test_utils import observation, tiny_config

from lerobot_sdp.benchmarks import cli, compiled
from lerobot_sdp.benchmarks.latency_measure import Clock
from lerobot_sdp.modeling_sdp import SDPPolicy


def test_quick_run_reports_eager_compiled_and_the_floor(tmp_path):
    torch._dynamo.reset()
    cli.main(["compiled", "--quick", "--device", "cpu", "--num_threads", "1", "--output_dir", str(tmp_path)])
    report = json.loads((tmp_path / "compiled.json").read_text())
    (result,) = report["results"]
    assert result["batch_size"] == 1
    for name in compiled.NAMES:
        assert result[name]["chunk_ms_p50"] > 0
        assert len(result[name]["chunk_ms_samples"]) == 1
    assert (
        result["sdp_eager"]["nfe_per_chunk"] == 2 and result["dp_eager"]["nfe_per_chunk"] == 4
    )  # DDIM4, h=2
    assert result["sdp_compiled_max_abs_action_diff"] < 1e-4
    assert result["sdp_unet_call_ms"]["eager"] > 0 and result["sdp_unet_call_ms"]["compiled"] > 0
    assert result["sdp_bookkeeping_ms"]["eager"] > 0 and result["sdp_bookkeeping_ms"]["compiled"] > 0
    assert set(result["sdp_bookkeeping_fraction_of_unet_call"]) == {"eager", "compiled"}
    bandwidth = report["memory_bandwidth_gb_s"] * 1e9
    assert report["bandwidth_floor_per_nfe_ms"] == pytest.approx(result["unet_bytes"] / bandwidth * 1000)
    with pytest.raises(SystemExit, match="exists"):
        cli.main(["compiled", "--quick", "--output_dir", str(tmp_path)])


@pytest.mark.parametrize("image", [False, True])
def test_unet_alone_runs_a_chunks_calls_on_the_streaming_inputs(image):
    """The U-Net timed alone gets what a streaming call gives it: the buffer's sample (then its own
    output) and the plan's own timesteps tensors in order (so the eager step-embedding cache serves it
    as it serves the stream), s calls per timed chunk after one warm-up chunk; with a camera too."""
    config = tiny_config(image=image)
    policy = SDPPolicy(config).eval()
    obs = observation(config, batch_size=1, seed=0)
    with torch.inference_mode():
        policy.select_action(obs)
        seen = []
        policy._sampling_model().unet.register_forward_hook(lambda m, args, out: seen.append((*args, out)))
        ms = compiled.unet_call_ms(policy, obs, Clock(torch.device("cpu")), repeats=3, compile_mode=None)
    plan = policy._buffer.plan(torch.device("cpu"), 1)
    assert ms > 0
    assert len(seen) == 4 * len(plan) == 4 * config.geometry.steps_per_call
    for i, (sample, timesteps, _) in enumerate(seen):
        assert timesteps is plan[i % len(plan)].timesteps
        previous_output = seen[i - 1][2]
        assert sample is (policy._buffer.sample if i % len(plan) == 0 else previous_output)


def test_bookkeeping_runs_the_stream_with_the_stand_in_then_restores_the_unet():
    """Inside `stand_in_unet` a chunk calls the stand-in s times and never the U-Net; afterwards the
    U-Net is back and the stream restarts (no buffer sampled by the stand-in survives)."""
    config = tiny_config()
    policy = SDPPolicy(config).eval()
    obs = observation(config, batch_size=1, seed=0)
    unet = policy._sampling_model().unet
    unet_calls = []
    unet.register_forward_hook(lambda *a: unet_calls.append(1))
    with torch.inference_mode():
        policy.select_action(obs)
        assert len(unet_calls) > 0
        unet_calls.clear()
        with compiled.stand_in_unet(policy):
            stand_in = policy._sampling_model().unet
            assert isinstance(stand_in, compiled.StandInUnet)
            stand_in_calls = []
            stand_in.register_forward_hook(lambda *a: stand_in_calls.append(1))
            for _ in range(2 * config.n_action_steps):  # two chunks of s calls (a zero primer calls none)
                policy.select_action(obs)
        assert unet_calls == []
        assert len(stand_in_calls) == 2 * config.geometry.steps_per_call
        assert policy._sampling_model().unet is unet
        assert policy._buffer.sample is None
