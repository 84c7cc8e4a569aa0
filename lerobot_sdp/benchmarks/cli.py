"""`lerobot-sdp-bench`: one subcommand per benchmark module.

A benchmark module exposes ``add_arguments(parser: argparse.ArgumentParser)`` and
``run(args: argparse.Namespace)``, and its docstring's first line is the subcommand's help.
Adding a benchmark = writing that module and adding one entry to ``SUBCOMMANDS``.
"""

import argparse
from types import ModuleType

from lerobot.utils.utils import init_logging

from . import (
    animation,
    compiled,
    data_parallel,
    delay,
    deployment,
    deployment_schedules,
    latency,
    probe,
    quality,
    server_load,
    throughput,
    train_profile,
)

SUBCOMMANDS: dict[str, ModuleType] = {
    "latency": latency,
    "compiled": compiled,
    "quality": quality,
    "train-profile": train_profile,
    "throughput": throughput,
    "data-parallel": data_parallel,
    "deployment": deployment,
    "delay": delay,
    "server-load": server_load,
    "animation": animation,
    "probe": probe,
    "schedules": deployment_schedules,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lerobot-sdp-bench",
        description="Benchmarks of Streaming Diffusion Policy against LeRobot's Diffusion Policy.",
    )
    subparsers = parser.add_subparsers(dest="subcommand", required=True)
    for name, module in SUBCOMMANDS.items():
        summary = (module.__doc__ or "").strip().splitlines()[0]
        sub = subparsers.add_parser(
            name,
            help=summary,
            description=module.__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(sub)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    init_logging()
    SUBCOMMANDS[args.subcommand].run(args)


if __name__ == "__main__":
    main()
