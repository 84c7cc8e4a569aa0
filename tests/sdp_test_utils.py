"""Small configs and observations shared by the tests."""

# lerobot-train's flags for the small SDP of `tiny_config` (state features come from the dataset)
TINY_POLICY_FLAGS = [
    "--policy.type=sdp",
    "--policy.down_dims=[16,32]",
    "--policy.diffusion_step_embed_dim=16",
    "--policy.n_action_steps=4",
    "--policy.num_inference_steps=10",
    "--policy.device=cpu",
]


def tiny_config(image: bool = False, **overrides):
    """A small SDP config with Push-T shaped features (state + keypoints, or state + 96 px camera)."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_sdp import SDPConfig

    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (2,))}
    if image:
        inputs["observation.image"] = PolicyFeature(FeatureType.VISUAL, (3, 32, 32))
    else:
        inputs["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (16,))
    kwargs = dict(
        down_dims=(16, 32),
        diffusion_step_embed_dim=16,
        n_action_steps=4,
        n_chunks=2,
        num_inference_steps=10,
        device="cpu",
        crop_shape=(28, 28) if image else None,
        spatial_softmax_num_keypoints=4,
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
    )
    kwargs.update(overrides)
    return SDPConfig(**kwargs)


def tiny_dp_config(**overrides):
    """LeRobot's Diffusion Policy at `tiny_config`'s size and features (horizon 8, 4 actions per chunk)."""
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    sdp = tiny_config()
    kwargs = dict(
        n_action_steps=4,
        horizon=8,
        down_dims=(16, 32),
        diffusion_step_embed_dim=16,
        num_inference_steps=4,
        device="cpu",
        input_features=sdp.input_features,
        output_features=sdp.output_features,
    )
    return DiffusionConfig(**(kwargs | overrides))


def observation(config, batch_size: int = 2, seed: int | None = None):
    """One environment step's (normalised) observation batch for `config`'s input features."""
    import torch

    gen = torch.Generator().manual_seed(seed) if seed is not None else None
    return {
        key: torch.rand((batch_size, *ft.shape), generator=gen) for key, ft in config.input_features.items()
    }


PUSHT_STATS = {
    "observation.state": {
        "min": [13.0, 32.0],
        "max": [496.0, 510.0],
        "mean": [250.0, 260.0],
        "std": [100.0, 90.0],
    },
    "action": {"min": [12.0, 25.0], "max": [511.0, 511.0], "mean": [250.0, 260.0], "std": [100.0, 90.0]},
}

KP_STATS = {"min": [0.0] * 16, "max": [512.0] * 16, "mean": [256.0] * 16, "std": [100.0] * 16}
PUSHT_KEYPOINT_STATS = {**PUSHT_STATS, "observation.environment_state": KP_STATS}


def save_tiny_policy(path, **overrides):
    """A random-weight SDP checkpoint with Push-T keypoint features (what `pusht_sim` observes) and its
    saved pre/post-processors."""
    from lerobot_sdp import SDPPolicy, make_sdp_pre_post_processors

    cfg = tiny_config(**overrides)
    SDPPolicy(cfg).save_pretrained(path)
    for pipeline in make_sdp_pre_post_processors(cfg, PUSHT_KEYPOINT_STATS):
        pipeline.save_pretrained(path)
    return path


def history(config, batch_size: int = 2):
    """A dataloader-style observation batch: (B, n_obs_steps, ...) per input feature."""
    obs = observation(config, batch_size)
    return {k: v.unsqueeze(1).expand(-1, config.n_obs_steps, *v.shape[1:]) for k, v in obs.items()}


PUSHT_TASK = "Push the T-shaped block onto the T-shaped target."


def make_tiny_pusht_dataset(
    root, image: bool = False, n_episodes: int = 2, length: int = 30, seed: int = 0, lengths=None, tasks=None
):
    """A small random LeRobotDataset with Push-T's schema (state + keypoints, or state + 96 px image);
    `lengths` gives every episode its own length (else n_episodes x length), `tasks` its own task
    string (else Push-T's for all)."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    if image:
        features["observation.image"] = {
            "dtype": "image",
            "shape": (96, 96, 3),
            "names": ["height", "width", "channel"],
        }
    else:
        features["observation.environment_state"] = {"dtype": "float32", "shape": (16,), "names": None}
    ds = LeRobotDataset.create("local/tiny_pusht", fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(seed)
    lengths = lengths or [length] * n_episodes
    for episode_length, task in zip(lengths, tasks or [PUSHT_TASK] * len(lengths), strict=True):
        for i in range(episode_length):
            frame = {
                "observation.state": rng.uniform(0, 512, 2).astype(np.float32),
                "action": rng.uniform(0, 512, 2).astype(np.float32),
                "next.reward": np.array([rng.uniform()], dtype=np.float32),
                "next.done": np.array([i == episode_length - 1]),
                "next.success": np.array([False]),
                "task": task,
            }
            if image:
                frame["observation.image"] = rng.integers(0, 255, (96, 96, 3), dtype=np.uint8)
            else:
                frame["observation.environment_state"] = rng.uniform(0, 512, 16).astype(np.float32)
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return ds


def stream_step_with(buffer, denoiser, generator=None, committed: int = 0):
    """One `StreamingBuffer.stream_step` with a plain denoiser of (sample, timesteps)."""
    from lerobot_sdp.buffer import bind

    return buffer.stream_step(bind(buffer.schedule, buffer.geometry, denoiser), generator, committed)


def tiny_job_config(shipped: str, path, policy: dict | None = None, **train) -> None:
    """A shipped training config shrunk to seconds (a tiny U-Net, 10 denoising steps, 2 training
    steps) and written to `path`, for end-to-end runs of the main jobs."""
    import json

    from lerobot_sdp import shipped_configs

    config = json.loads(shipped_configs.path(shipped).read_text())
    config["policy"] |= {
        "down_dims": [16, 32],
        "diffusion_step_embed_dim": 16,
        "n_action_steps": 4,
        "num_train_timesteps": 10,
        "num_inference_steps": 10,
        "scheduler_warmup_steps": 0,
        **(policy or {}),
    }
    config |= {"steps": 2, "batch_size": 4, "log_freq": 1, **train}
    path.write_text(json.dumps(config))
