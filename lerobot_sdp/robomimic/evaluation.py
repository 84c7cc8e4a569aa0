"""How robomimic tasks are evaluated here: `lerobot-eval --env.type=robomimic` from fixed episode seeds
(the main job's and the quality benchmark's). Scripted demonstrations use seeds from 100000 on, so
every evaluation scene is unseen."""

from ..lerobot_cli import eval_flags

EVAL_SEED = 1000  # episode i of an evaluation starts from seed EVAL_SEED + i


def robomimic_eval_args(
    task: str, n_episodes: int, device: str, episode_length: int | None = None, seed: int = EVAL_SEED
) -> list[str]:
    """robomimic evaluation, 25 envs a batch."""
    env = ["--env.type=robomimic", f"--env.task={task}"]
    return eval_flags(env, n_episodes, 25, device, seed, episode_length)
