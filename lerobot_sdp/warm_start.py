"""Warm start: turn a trained LeRobot Diffusion Policy checkpoint into SDP's initial weights.

`--policy.init_from=PATH_OR_HUB_ID` names a LeRobot `diffusion` checkpoint: a local `pretrained_model`
folder (config.json + model.safetensors; a training checkpoint folder holding one works too) or a Hub
id, fetched with `huggingface_hub.snapshot_download`. SDP's network is DP's (observation encoders,
U-Net blocks with their FiLM cond encoders, final conv) with a different step encoder, so every DP
tensor `diffusion.X` is copied into SDP's `model.X` (and into the EMA copy): with
`step_conditioning="film_per_slot"` DP's step encoder too; with the paper's flattened encoder, which
has no DP counterpart, it is initialised from DP's so that every slot at one level gives DP's
embedding. A checkpoint that does not fit (another action dimension, other cameras or state, other
U-Net sizes, not a `diffusion` checkpoint) is a ValueError naming the difference and the fix.

Normalisation lives in LeRobot's processor pipeline, not in the model: the checkpoint's normaliser
statistics (`policy_preprocessor.json` and its safetensors) are what the copied weights were trained
with, so `make_sdp_pre_post_processors` and the constant primer use them (`normalizer_stats`).
"""

import json
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import torch
from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE
from lerobot.utils.constants import POLICY_PREPROCESSOR_DEFAULT_NAME
from safetensors.torch import load_file
from torch import Tensor, nn

from .configuration_sdp import SDPConfig
from .unet import PerSlotStepEncoder, flatten_encoder_from_dp

PREPROCESSOR_NAME = f"{POLICY_PREPROCESSOR_DEFAULT_NAME}.json"
DP_PREFIX = "diffusion."
STEP_ENCODER = "unet.diffusion_step_encoder."

# DP config fields that shape the copied network; a difference names the option to pass.
ARCHITECTURE_FIELDS = (
    "n_obs_steps",  # the FiLM input holds n_obs_steps observations
    "down_dims",
    "kernel_size",
    "n_groups",
    "diffusion_step_embed_dim",
    "use_film_scale_modulation",
)
VISION_FIELDS = (  # only with cameras
    "vision_backbone",
    "use_group_norm",
    "spatial_softmax_num_keypoints",
    "use_separate_rgb_encoder_per_camera",
    "crop_shape",
    "resize_shape",
    "crop_ratio",
)
# Fields that change what the copied U-Net's output means: an error, not a warning.
PREDICTION_FIELDS = ("prediction_type",)
SCHEDULE_FIELDS = ("num_train_timesteps", "beta_schedule", "beta_start", "beta_end")


@dataclass
class WarmStartReport:
    """What a warm start did, keyed by SDP's `model.*` tensor names (the EMA copy gets the same)."""

    source: str
    checkpoint: Path  # the local folder the weights came from
    copied: list[str] = field(default_factory=list)
    initialised: dict[str, str] = field(default_factory=dict)  # tensor -> why it was not copied
    unused: list[str] = field(default_factory=list)  # DP tensors SDP has no place for

    def summary(self) -> str:
        def groups(keys) -> str:
            counts = Counter(_module_group(k) for k in keys)
            return ", ".join(f"{name} ({n})" for name, n in sorted(counts.items()))

        lines = [
            f"Warm start from the Diffusion Policy checkpoint {self.source}:",
            f"  copied {len(self.copied)} tensors into model and ema_model: {groups(self.copied)}",
        ]
        for reason in sorted(set(self.initialised.values())):
            keys = [k for k, r in self.initialised.items() if r == reason]
            lines.append(f"  initialised {len(keys)} tensors ({groups(keys)}): {reason}")
        if self.unused:
            lines.append(f"  not used from the checkpoint: {', '.join(self.unused)}")
        return "\n".join(lines)


def _module_group(key: str) -> str:
    parts = key.split(".")
    return ".".join(parts[:2]) if parts[0] == "unet" else parts[0]


def resolve_checkpoint(init_from: str | Path) -> Path:
    """The local `pretrained_model` folder of `init_from` (a folder, a training checkpoint folder that
    holds `pretrained_model/`, or a Hub id, downloaded)."""
    path = Path(init_from).expanduser()
    if path.is_dir():
        if not (path / CONFIG_NAME).is_file() and (path / "pretrained_model" / CONFIG_NAME).is_file():
            path = path / "pretrained_model"
        if not (path / CONFIG_NAME).is_file() or not (path / SAFETENSORS_SINGLE_FILE).is_file():
            raise ValueError(
                f"init_from={init_from!r} is a folder without {CONFIG_NAME} and {SAFETENSORS_SINGLE_FILE}: "
                "point it at a Diffusion Policy checkpoint's `pretrained_model` folder (e.g. "
                "outputs/train/dp/checkpoints/last/pretrained_model) or a Hub id."
            )
        return path
    if path.exists() or str(init_from).count("/") != 1:
        raise ValueError(
            f"init_from={init_from!r} is neither a checkpoint folder nor a Hub id (`owner/name`): point it "
            "at a Diffusion Policy checkpoint's `pretrained_model` folder or its Hub repository."
        )
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(repo_id=str(init_from)))


def _as_tuple(value):
    return tuple(value) if isinstance(value, list | tuple) else value


def _features(features: dict) -> dict[str, tuple]:
    """{key: shape} of config.json's or a config's feature dict."""
    out = {}
    for key, ft in features.items():
        shape = ft["shape"] if isinstance(ft, dict) else ft.shape
        out[key] = tuple(shape)
    return out


def check_compatible(dp: dict, config: SDPConfig, source: str) -> None:
    """Raise a ValueError naming the first difference that stops DP's weights from fitting `config`."""
    kind = dp.get("type")
    if kind != "diffusion":
        raise ValueError(
            f"init_from={source!r} is a {kind!r} checkpoint, not a LeRobot `diffusion` one: SDP can only "
            "warm start from Diffusion Policy (same U-Net). Train DP with --policy.type=diffusion, or drop "
            "--policy.init_from."
        )
    dp_out, sdp_out = _features(dp.get("output_features", {})), _features(config.output_features)
    if dp_out != sdp_out:
        raise ValueError(
            f"init_from={source!r}: the checkpoint's actions are {dp_out} but SDP's are {sdp_out} (another "
            "action dimension): warm start from a Diffusion Policy trained on this robot's actions."
        )
    dp_in, sdp_in = _features(dp.get("input_features", {})), _features(config.input_features)
    if dp_in != sdp_in:
        only_dp = sorted(dp_in.keys() - sdp_in.keys())
        only_sdp = sorted(sdp_in.keys() - dp_in.keys())
        reshaped = sorted(k for k in dp_in.keys() & sdp_in.keys() if dp_in[k] != sdp_in[k])
        details = "; ".join(
            part
            for part in (
                f"only in the checkpoint: {only_dp}" if only_dp else "",
                f"only in SDP: {only_sdp}" if only_sdp else "",
                ", ".join(f"{k}: checkpoint {dp_in[k]} vs SDP {sdp_in[k]}" for k in reshaped),
            )
            if part
        )
        raise ValueError(
            f"init_from={source!r}: the observation features differ ({details}). Train SDP on the "
            "cameras and state the Diffusion Policy was trained on (same dataset, or --rename_map)."
        )
    fields = ARCHITECTURE_FIELDS + (VISION_FIELDS if config.image_features else ()) + PREDICTION_FIELDS
    differences = [
        name for name in fields if name in dp and _as_tuple(dp[name]) != _as_tuple(getattr(config, name))
    ]
    if differences:
        found = "; ".join(
            f"`{n}` is {_as_tuple(dp[n])!r} there, {_as_tuple(getattr(config, n))!r} here"
            for n in differences
        )
        flags = " ".join(f"--policy.{n}={_flag_value(dp[n])}" for n in differences)
        raise ValueError(
            f"init_from={source!r}: the checkpoint's network differs from the SDP config's ({found}), so its "
            f"weights do not fit. Pass {flags} (as the checkpoint)."
        )
    _check_normalization(dp, config, source)
    for name in SCHEDULE_FIELDS:
        if name in dp and _as_tuple(dp[name]) != _as_tuple(getattr(config, name)):
            logging.warning(
                "Warm start: `%s` is %r in the checkpoint but %r in the SDP config: the copied U-Net "
                "learned another noise schedule and needs retraining to fit this one.",
                name,
                dp[name],
                getattr(config, name),
            )


def _check_normalization(dp: dict, config: SDPConfig, source: str) -> None:
    """The copied U-Net predicts actions (and reads states) in the space its normaliser made: another
    mode (e.g. MEAN_STD actions where SDP uses MIN_MAX) would feed it a different space."""
    theirs = {k: str(v) for k, v in dp.get("normalization_mapping", {}).items()}
    ours = {k: v.value for k, v in config.normalization_mapping.items()}
    differ = sorted(k for k in theirs.keys() & ours.keys() if theirs[k] != ours[k])
    if differ:
        found = "; ".join(f"{k}: {theirs[k]} there, {ours[k]} here" for k in differ)
        raise ValueError(
            f"init_from={source!r}: the checkpoint normalises differently ({found}), so its weights work "
            f"in another space. Set SDP's \"normalization_mapping\" to the checkpoint's {theirs} (in the "
            "config file, `policy.normalization_mapping`), or warm start from a DP trained with SDP's."
        )


def _flag_value(value) -> str:
    """`value` as a `--policy.*` command-line value (JSON lists without spaces)."""
    return value if isinstance(value, str) else json.dumps(value, separators=(",", ":"))


def _base_key(key: str) -> str:
    """A DP state-dict key without `_orig_mod.` (DP's `compile_model` compiles its U-Net in place)."""
    return key.replace("_orig_mod.", "")


@torch.no_grad()
def warm_start(policy: nn.Module, init_from: str) -> WarmStartReport:
    """Copy a DP checkpoint's weights into `policy.model` (and `policy.ema_model`); log and return the
    report."""
    config: SDPConfig = policy.config
    path = resolve_checkpoint(init_from)
    dp_config = json.loads((path / CONFIG_NAME).read_text())
    check_compatible(dp_config, config, init_from)
    dp_state = {
        _base_key(k.removeprefix(DP_PREFIX)): v
        for k, v in load_file(path / SAFETENSORS_SINGLE_FILE).items()
        if k.startswith(DP_PREFIX)
    }
    model = policy.model
    target = model.state_dict()
    report = WarmStartReport(source=init_from, checkpoint=path)
    mismatched = [
        f"{k}: checkpoint {tuple(dp_state[k].shape)} vs SDP {tuple(v.shape)}"
        for k, v in target.items()
        if k in dp_state and dp_state[k].shape != v.shape
    ]
    if mismatched:
        raise ValueError(
            f"init_from={init_from!r}: {len(mismatched)} tensors do not fit "
            f"(e.g. {'; '.join(mismatched[:3])}). "
            "Set the SDP architecture options (--policy.down_dims, ...) to the checkpoint's config.json."
        )
    for key, tensor in target.items():
        if key in dp_state:
            tensor.copy_(dp_state[key])
            report.copied.append(key)

    unet = model.unet
    flatten = isinstance(unet.diffusion_step_encoder, PerSlotStepEncoder)
    if flatten:
        dp_encoder = {
            k.removeprefix(STEP_ENCODER): v for k, v in dp_state.items() if k.startswith(STEP_ENCODER)
        }
        flatten_encoder_from_dp(unet.diffusion_step_encoder, dp_encoder)
        for key in target:
            if key.startswith(STEP_ENCODER):
                report.initialised[key] = (
                    "the paper's flattened per-slot step encoder (step_conditioning=flatten) has no DP "
                    "counterpart: set from DP's step encoder (first layer divided among the slots) so every "
                    "slot at one level gives DP's embedding"
                )
    for key in target:
        if key not in dp_state and key not in report.initialised:
            report.initialised[key] = "no tensor of this name in the checkpoint: kept SDP's initialisation"
    report.unused = sorted(
        k for k in dp_state if k not in target and not (k.startswith(STEP_ENCODER) and flatten)
    )
    if policy.ema_model is not None:
        policy.ema_model.load_state_dict(model.state_dict())
    logging.info(report.summary())
    return report


def normalizer_stats(init_from: str | Path) -> dict[str, dict[str, Tensor]] | None:
    """The normaliser statistics saved with a LeRobot checkpoint (its `policy_preprocessor.json`
    pipeline's normalizer step), as {feature: {stat: tensor}}; None when it has none (a model saved
    with `save_pretrained` alone)."""
    path = resolve_checkpoint(init_from)
    if not (path / PREPROCESSOR_NAME).is_file():
        return None
    steps = json.loads((path / PREPROCESSOR_NAME).read_text()).get("steps", [])
    for step in steps:
        if step.get("registry_name") == "normalizer_processor" and step.get("state_file"):
            stats: dict[str, dict[str, Tensor]] = {}
            for flat_key, tensor in load_file(path / step["state_file"]).items():
                key, stat = flat_key.rsplit(".", 1)
                stats.setdefault(key, {})[stat] = tensor
            return stats
    return None


def merged_stats(init_from: str | Path, dataset_stats: dict | None, warn: bool = True) -> dict | None:
    """The statistics a warm-started SDP normalises with: the checkpoint's (what its weights were
    trained with) over the dataset's; with `warn`, a warning names the features where they differ."""
    saved = normalizer_stats(init_from)
    if saved is None:
        if warn:
            logging.warning(
                "Warm start: %s holds no normaliser statistics (no %s); SDP normalises with the dataset's. "
                "They equal DP's only if DP was trained on this dataset.",
                init_from,
                PREPROCESSOR_NAME,
            )
        return dataset_stats
    differ = sorted(
        key for key in saved.keys() & (dataset_stats or {}).keys() if _differ(saved[key], dataset_stats[key])
    )
    if warn and differ:
        logging.warning(
            "Warm start: the dataset's statistics of %s differ from the checkpoint's; SDP normalises with "
            "the checkpoint's, which its copied weights were trained with.",
            differ,
        )
    return {**(dataset_stats or {}), **saved}


def _differ(saved: dict[str, Tensor], other: dict) -> bool:
    for name, value in saved.items():
        if name not in other:
            continue
        theirs = torch.as_tensor(other[name], dtype=torch.float32).flatten()
        if theirs.shape != value.flatten().shape or not torch.allclose(
            theirs, value.float().flatten(), 1e-4, 1e-6
        ):
            return True
    return False
