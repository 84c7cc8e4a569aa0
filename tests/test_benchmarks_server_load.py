"""`lerobot-sdp-bench server-load` on a tiny SDP: the real server CLI, N RobotClients each on its own
connection and session, every robot's episode run to its end (plumbing, not timed)."""

import json

import pytest
from sdp_test_utils import save_tiny_policy

from lerobot_sdp.benchmarks import cli


@pytest.mark.slow
def test_each_client_gets_its_own_session_and_runs_its_episode(tmp_path):
    policy = save_tiny_policy(tmp_path / "sdp")
    out = tmp_path / "out"
    port = 20000 + (hash(str(tmp_path)) % 2000)
    cli.main(["server-load", "--policy", f"tiny={policy}", "--clients", "1", "2", "--episode_length", "12",
              "--port", str(port), "--output_dir", str(out)])  # fmt: skip
    result = json.loads((out / "results.json").read_text())
    assert [r["clients"] for r in result["rows"]] == [1, 2]
    for row in result["rows"]:
        assert row["episodes_over"] == row["clients"], row  # every client was served to its episode's end
        assert 1 <= row["ticks_mean"] <= 12 and row["missed_ticks_max"] >= 0 and row["longest_gap_s"] > 0
    # two sessions: the server loaded the policy once per client
    log = (out / "logs" / "server_2_clients.log").read_text()
    assert log.count("Receiving policy instructions") == 2, log[-2000:]
    assert (out / "results.md").read_text().count("\n| ") == 3


def test_one_policy_and_positive_client_counts(tmp_path):
    policy = save_tiny_policy(tmp_path / "sdp")
    with pytest.raises(SystemExit, match="one --policy"):
        cli.main(["server-load", "--policy", f"a={policy}", "--policy", f"b={policy}"])
    with pytest.raises(SystemExit, match="at least 1"):
        cli.main(["server-load", "--policy", f"a={policy}", "--clients", "0"])
