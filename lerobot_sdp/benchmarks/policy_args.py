"""`--policy NAME=PATH`, as the benchmarks that compare trained checkpoints take them."""

import argparse
from pathlib import Path


def add_policy_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--policy",
        action="append",
        required=True,
        metavar="NAME=PATH",
        help="a trained pretrained_model folder, named for the table (repeat for each policy)",
    )


def parse_policies(specs: list[str]) -> dict[str, Path]:
    """{NAME: pretrained_model folder}, refusing a spec without a name or a folder without config.json."""
    policies = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"--policy takes NAME=PATH (a pretrained_model folder), got {spec!r}.")
        if not (Path(path) / "config.json").exists():
            raise SystemExit(f"--policy {name}: {path} has no config.json; pass a pretrained_model folder.")
        policies[name] = Path(path)
    return policies
