"""What every benchmark writes: markdown tables of formatted cells, figures with their standard
errors, and the JSON result file (written after every cell, so a stopped run keeps what it measured)."""

import json
from collections.abc import Iterable, Sequence
from pathlib import Path


def table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    """Markdown table lines: the header, its separator, one line per row of already formatted cells."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows]


def with_se(row: dict, key: str, digits: int) -> str:
    """`row[key]` with its standard error (`row[key + "_se"]`) when the row has one."""
    value = f"{row[key]:.{digits}f}"
    return f"{value} ± {row[key + '_se']:.{digits}f}" if key + "_se" in row else value


def write_json(path: Path, report: dict) -> None:
    """The report as indented JSON (paths and other objects written as their str)."""
    path.write_text(json.dumps(report, indent=2, default=str))
