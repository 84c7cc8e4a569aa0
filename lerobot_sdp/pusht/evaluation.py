"""How Push-T is evaluated here: LeRobot's gym-pusht env on keypoint observations, from fixed episode
seeds (the main job's and every benchmark's), through `lerobot-eval`."""

OBS_TYPE = "environment_state_agent_pos"
EVAL_SEED = 100_000  # episode i of an evaluation starts from seed EVAL_SEED + i


def pusht_eval_args(
    obs_type: str, n_episodes: int, seed: int, device: str, episode_length: int | None = None
) -> list[str]:
    """Push-T evaluation on batched sync envs (async Push-T envs are broken in lerobot 0.6.1)."""
    args = [
        "--env.type=pusht",
        f"--env.obs_type={obs_type}",
        f"--eval.n_episodes={n_episodes}",
        f"--eval.batch_size={min(n_episodes, 50)}",
        "--eval.use_async_envs=false",
        f"--policy.device={device}",
        f"--seed={seed}",
    ]
    return args + ([f"--env.episode_length={episode_length}"] if episode_length else [])
