"""How Push-T is evaluated here: LeRobot's gym-pusht env on keypoint observations, from fixed episode
seeds (the main job's and every benchmark's), through `lerobot-eval`."""

from ..lerobot_cli import eval_flags

OBS_TYPE = "environment_state_agent_pos"
EVAL_SEED = 100_000  # episode i of an evaluation starts from seed EVAL_SEED + i


def pusht_eval_args(
    obs_type: str, n_episodes: int, seed: int, device: str, episode_length: int | None = None
) -> list[str]:
    """Push-T evaluation, 50 envs a batch (sync: async Push-T envs are broken in lerobot 0.6.1)."""
    env = ["--env.type=pusht", f"--env.obs_type={obs_type}"]
    return eval_flags(env, n_episodes, 50, device, seed, episode_length)
