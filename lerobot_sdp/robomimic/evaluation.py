"""How robomimic tasks are evaluated here: `lerobot-eval --env.type=robomimic` from fixed episode seeds
(the main job's and the quality benchmark's). Scripted demonstrations use seeds from 100000 on, so
every evaluation scene is unseen."""

EVAL_SEED = 1000  # episode i of an evaluation starts from seed EVAL_SEED + i


def robomimic_eval_args(
    task: str, n_episodes: int, device: str, episode_length: int | None = None, seed: int = EVAL_SEED
) -> list[str]:
    """robomimic evaluation on batched sync envs (on a few cores, async workers only compete for them)."""
    args = [
        "--env.type=robomimic",
        f"--env.task={task}",
        f"--eval.n_episodes={n_episodes}",
        f"--eval.batch_size={min(n_episodes, 25)}",
        "--eval.use_async_envs=false",
        f"--policy.device={device}",
        f"--seed={seed}",
    ]
    return args + ([f"--env.episode_length={episode_length}"] if episode_length else [])
