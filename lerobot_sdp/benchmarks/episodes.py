"""Task figures over evaluation episodes, as every benchmark reports them."""

import math
import statistics


def figures(max_rewards: list[float], successes: list[bool]) -> dict:
    """avg_max_reward with its standard error over episodes, pc_success with its binomial s.e."""
    n = len(max_rewards)
    if n == 0:
        raise ValueError("No episodes to summarise.")
    p = sum(map(bool, successes)) / n
    return {
        "avg_max_reward": statistics.fmean(max_rewards),
        "avg_max_reward_se": statistics.stdev(max_rewards) / math.sqrt(n) if n > 1 else 0.0,
        "pc_success": 100 * p,
        "pc_success_se": 100 * math.sqrt(p * (1 - p) / n),
        "n_episodes": n,
    }
