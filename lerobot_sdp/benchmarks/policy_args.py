"""The arguments benchmarks share: `--policy NAME=PATH` for those that compare trained checkpoints,
a training config and a local dataset for those that time training."""

import argparse
from pathlib import Path

from .. import shipped_configs


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


DEFAULT_CONFIG = "pusht_state_cpu"


def configs(args: argparse.Namespace) -> list[Path]:
    """`--config_path` of `add_training_arguments(several_configs=True)` as a list, the default too."""
    return args.config_path if isinstance(args.config_path, list) else [args.config_path]


def add_training_arguments(p: argparse.ArgumentParser, several_configs: bool = False) -> None:
    """`--config_path` (a file or a shipped config's name; one or more with ``several_configs``),
    `--dataset_root`, `--repo_id`."""
    p.add_argument(
        "--config_path",
        type=shipped_configs.config_argument,
        nargs="+" if several_configs else None,
        default=DEFAULT_CONFIG,  # argparse applies the type to it: a path, a list of one after configs()
        help="a config file, or the name of a shipped one (python -m lerobot_sdp.shipped_configs)",
    )
    add_dataset_arguments(p)


def add_dataset_arguments(p: argparse.ArgumentParser) -> None:
    """`--dataset_root` (required) and `--repo_id` of a local LeRobotDataset."""
    p.add_argument(
        "--dataset_root", type=Path, required=True, help="local LeRobotDataset (e.g. the converted zarr)"
    )
    p.add_argument("--repo_id", default="local/pusht_keypoints")
