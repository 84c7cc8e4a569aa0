"""What SDPPolicy accepts as input, checked before it acts: observation features with their trained
shapes, finite values, no keyword it would silently ignore; and the (B, n_obs_steps, ...) history it
conditions on, from a dataloader batch or a single frame. Errors name the key and the fix."""

import torch
from lerobot.utils.constants import OBS_IMAGES
from torch import Tensor

from .configuration_sdp import SDPConfig


def reject_unknown_kwargs(method: str, kwargs: dict) -> None:
    """LeRobot passes extra keywords through `**kwargs`; SDP refuses what it would silently ignore."""
    if not kwargs:
        return
    hint = (
        " SDP draws fresh noise into its buffer on every chunk, so one initial noise tensor cannot fix "
        "its actions: pass `generator=torch.Generator(device).manual_seed(...)` for reproducible actions."
        if "noise" in kwargs
        else ""
    )
    raise TypeError(
        f"SDPPolicy.{method}() got unexpected keyword argument(s) {sorted(kwargs)}; it accepts "
        f"`generator`.{hint}"
    )


def check_observation(config: SDPConfig, batch: dict[str, Tensor], time_axis: bool) -> None:
    """Every input feature present with its trained shape ((B, To, *shape) with ``time_axis``)."""
    to = (config.n_obs_steps,) if time_axis else ()
    for key, ft in config.input_features.items():
        if key not in batch:
            raise ValueError(
                f"Observation is missing `{key}`; this policy was trained on "
                f"{sorted(config.input_features)}. Check the environment's observation type "
                "(e.g. `--env.obs_type`) or the processor's rename map."
            )
        value = batch[key]
        if not isinstance(value, Tensor) or tuple(value.shape[1:]) != (*to, *ft.shape):
            shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(
                f"Observation `{key}` has shape {shape}, expected "
                f"(batch, {', '.join(map(str, (*to, *ft.shape)))}). "
                "Check the environment (or dataset) matches the training data."
            )


def stack_cameras(config: SDPConfig, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """The cameras stacked under `observation.images`, as LeRobot's DP encoder reads them."""
    if not config.image_features:
        return batch
    batch = dict(batch)
    batch[OBS_IMAGES] = torch.stack([batch[key] for key in config.image_features], dim=-4)
    return batch


def offline_history(config: SDPConfig, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """A dataloader batch, as LeRobot's Diffusion Policy takes it: (B, To, ...) per input feature
    (extra keys such as `task`, `index` or `action` are ignored); with To = 1 the time axis may be
    absent, as a (B, C, H, W) image."""
    history = {}
    for key, value in batch.items():
        ft = config.input_features.get(key)
        if ft is None:
            continue
        no_time_axis = isinstance(value, Tensor) and value.ndim == len(ft.shape) + 1
        history[key] = value.unsqueeze(1) if config.n_obs_steps == 1 and no_time_axis else value
    check_observation(config, history, time_axis=True)
    return stack_cameras(config, history)


def repeated_frame(config: SDPConfig, frame: dict[str, Tensor]) -> dict[str, Tensor]:
    """One frame (B, ...) as a history of n_obs_steps copies (an engine that sees no other tick)."""
    to = config.n_obs_steps
    inputs = {k: v for k, v in frame.items() if k in config.input_features}
    repeated = {k: v.unsqueeze(1).expand(-1, to, *v.shape[1:]) for k, v in inputs.items()}
    return offline_history(config, repeated)


def finite_flags(history: dict[str, Tensor]) -> Tensor:
    """One flag per observation key: True where every value is finite (computed on the device)."""
    return torch.stack([torch.isfinite(value).all() for value in history.values()])


def refuse_non_finite(history: dict[str, Tensor], finite: Tensor) -> None:
    """Raise, naming the keys, when an observation held NaN or inf (read after the chunk is computed:
    the check costs one host read)."""
    bad = [f"`{key}`" for key, ok in zip(history, finite.tolist(), strict=True) if not ok]
    if bad:
        raise ValueError(f"Observation {', '.join(bad)} contains NaN or inf; refusing to act on it.")
