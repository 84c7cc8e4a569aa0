"""The benchmarks' shared writers: markdown tables, figures with standard errors, JSON results."""

import json
from pathlib import Path

from lerobot_sdp.benchmarks.report import table, with_se, write_json


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
