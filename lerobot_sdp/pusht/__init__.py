"""The Push-T task: the zarr converter (`lerobot-sdp-convert-pusht`, `convert.py`), where training data
comes from (`data.py`), how it is evaluated (`evaluation.py`) and the main job (`lerobot-sdp-pusht`,
`job.py`).

Push-T's env itself is LeRobot's (`--env.type=pusht`, gym-pusht); importing this package loads nothing.
"""
