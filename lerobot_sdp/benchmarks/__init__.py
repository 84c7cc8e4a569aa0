"""Benchmarks of SDP against LeRobot's Diffusion Policy, run through `lerobot-sdp-bench <subcommand>`.

Each subcommand is one module exposing ``add_arguments(parser)`` and ``run(args)``; ``cli.py`` lists
them.
"""
