"""Small configs and observations shared by the tests."""


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
        down_dims=(16, 32), diffusion_step_embed_dim=16, n_action_steps=4, n_chunks=2,
        num_inference_steps=10, device="cpu", crop_shape=(28, 28) if image else None,
        spatial_softmax_num_keypoints=4,
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
    )
    kwargs.update(overrides)
    return SDPConfig(**kwargs)


def observation(config, batch_size: int = 2, seed: int | None = None):
    """One environment step's (normalised) observation batch for `config`'s input features."""
    import torch

    gen = torch.Generator().manual_seed(seed) if seed is not None else None
    return {
        key: torch.rand((batch_size, *ft.shape), generator=gen) for key, ft in config.input_features.items()
    }


PUSHT_STATS = {
    "observation.state": {"min": [13.0, 32.0], "max": [496.0, 510.0], "mean": [250.0, 260.0], "std": [100.0, 90.0]},
    "action": {"min": [12.0, 25.0], "max": [511.0, 511.0], "mean": [250.0, 260.0], "std": [100.0, 90.0]},
}


def history(config, batch_size: int = 2):
    """A dataloader-style observation batch: (B, n_obs_steps, ...) per input feature."""
    obs = observation(config, batch_size)
    return {k: v.unsqueeze(1).expand(-1, config.n_obs_steps, *v.shape[1:]) for k, v in obs.items()}
