"""`lerobot-sdp-bench compiled` end to end on its CI-sized run: four policies timed, SDP's compiled
actions equal its eager ones, the floor derived from the measured bandwidth (values sane, not timed)."""

import json

import pytest
import torch

from lerobot_sdp.benchmarks import cli, compiled


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
    bandwidth = report["memory_bandwidth_gb_s"] * 1e9
    assert report["bandwidth_floor_per_nfe_ms"] == pytest.approx(result["unet_bytes"] / bandwidth * 1000)
    with pytest.raises(SystemExit, match="exists"):
        cli.main(["compiled", "--quick", "--output_dir", str(tmp_path)])
