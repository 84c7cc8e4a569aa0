"""The benchmarks' shared writers: markdown tables, figures with standard errors, JSON results."""

import json
from pathlib import Path

from lerobot_sdp.benchmarks.report import (
    reward_success_plot,
    save_figure,
    table,
    with_se,
    write_json,
)


def test_a_table_has_its_header_separator_and_one_line_per_row():
    lines = table(["run", "reward"], [["dp", "0.500"], ["sdp", 0.75]])
    assert lines == ["| run | reward |", "|---|---|", "| dp | 0.500 |", "| sdp | 0.75 |"]
    assert table(["a"], []) == ["| a |", "|---|"]


def test_a_figure_carries_its_standard_error_when_it_has_one():
    assert with_se({"r": 0.51234, "r_se": 0.0456}, "r", 3) == "0.512 ± 0.046"
    assert with_se({"r": 0.51234}, "r", 1) == "0.5"


def test_results_are_indented_json_with_paths_as_text(tmp_path):
    write_json(tmp_path / "results.json", {"path": Path("/x/y"), "rows": [1]})
    text = (tmp_path / "results.json").read_text()
    assert json.loads(text) == {"path": "/x/y", "rows": [1]} and text.startswith("{\n  ")


def test_a_log_x_figure_is_labelled_at_its_points_apart(tmp_path):
    series = {  # latencies within one decade: matplotlib's own minor labels would overlap here
        "dp": [{"ms": 15.7, "pc_success": 44.0}, {"ms": 31.8, "pc_success": 96.0}],
        "sdp_h2": [{"ms": 19.4, "pc_success": 78.0}],  # too close to 15.7 for a label of its own
        "sdp_h4": [{"ms": 62.04, "pc_success": 92.0}],
    }
    fig, axes = reward_success_plot(
        {k: [p | {"avg_max_reward": p["pc_success"] / 100} for p in v] for k, v in series.items()},
        [("ms", "latency (ms)", 1)],
        "t",
        log_x=True,
    )
    fig.canvas.draw()
    for ax in axes[:, 0]:
        assert ax.get_xscale() == "log"
        assert [t.get_text() for t in ax.get_xticklabels()] == ["15.7", "31.8", "62"]
        assert all(not t.get_text() for t in ax.get_xticklabels(minor=True))
    save_figure(fig, tmp_path / "cost.png")
