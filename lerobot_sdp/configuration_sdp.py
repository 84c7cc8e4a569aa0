"""Configuration of Streaming Diffusion Policy (`--policy.type=sdp`).

Field names are LeRobot Diffusion Policy's wherever the meaning is the same, so a DP command line
carries over; SDP adds `n_chunks` (the paper's h), `action_primer`, `noise_schemes` and EMA. The
horizon is not a field: it follows from n_obs_steps, n_action_steps and n_chunks (see
`geometry.ChunkGeometry`) and is reported in the log. Fields are a saved format: renaming or
removing one breaks loading older checkpoints.
"""

import logging
from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig, DiffuserSchedulerConfig, OptimizerConfig

from .geometry import ChunkGeometry
from .noise_schemes import CHUNKWISE_GRIDS, NoiseCurriculum, NoiseSchemeWeights

ACTION_PRIMERS = ("zero", "constant", "denoise")
STEP_CONDITIONINGS = ("flatten", "film_per_slot")
SAMPLINGS = ("stream", "fresh", "full_denoise")


def _check_choice(name: str, value: str, choices) -> None:
    if value not in choices:
        raise ValueError(f"`{name}` must be one of {list(choices)}, got {value!r}.")


@OptimizerConfig.register_subclass("adam_fused")
@dataclass
class FusedAdamConfig(AdamConfig):
    """LeRobot's Adam, built with torch's fused kernel: one pass over every weight instead of a loop over
    the U-Net's 148 tensors (the Push-T config's optimizer step: 7.6 ms -> 3.3 ms on a 2-core CPU,
    docs/benchmarks.md). The same update up to float rounding."""

    fused: bool = True


@PreTrainedConfig.register_subclass("sdp")
@dataclass
class SDPConfig(PreTrainedConfig):
    """Streaming Diffusion Policy (Høeg, Du, Egeland, arXiv 2406.04806).

    SDP-specific:
        n_chunks: chunks in the streaming buffer (h). Each executed chunk costs N / h denoiser calls.
        action_primer: buffer initialisation after reset: "zero" (paper default), "constant" (the
            current state repeated, needs state and action in one space), "denoise" (a full N-step
            denoise on the first call).
        noise_schemes: training mixture weights of the corruption schemes constant / linear /
            independent / chunkwise / independent_chunks (default 0.2 constant + 0.8 chunkwise, the
            paper's best).
        chunkwise_grid: where the chunk-wise scheme draws its levels: "sampler" (the default: the
            inference sampler's N-step grid, s level staircases) or "training_table" (all
            num_train_timesteps, T/h staircases, as the authors' code; needs T divisible by h).
        noise_curriculum: constant levels for the first `constant_steps` optimiser steps, then the
            mixture, reached linearly over `ramp_steps` (a switch when 0). Off by default (all 0).
        min_snr_gamma: Min-SNR-gamma loss weighting per slot (Hang et al. 2023). 5.0 (the default):
            near-clean slots count less, which lets SDP h = 2 learn robomimic Can from scratch as
            fast as DP (docs/algorithm.md). None: every slot weighs the same, the paper's Eq. 5.
        use_ema, ema_power, ema_max_decay: EMA of the weights, used for inference in eval mode.
        step_conditioning: how the per-slot noise levels condition the U-Net. "flatten" (the paper):
            the slots' step embeddings are flattened into one vector (ties the network to its horizon).
            "film_per_slot": each slot's level goes through DP's own step encoder and conditions its own
            position through the blocks' FiLM (pooled to each U-Net level); with every slot at one
            level this is exactly DP's network, so DP's weights all carry over (`unet.py`).
        max_delay: the largest inference delay, in control ticks, the policy is trained for. A chunk
            requested at tick t while d <= max_delay actions of the current chunk are still to run is
            denoised with those d actions as clean, committed slots after the observation, and starts
            at t + d (`geometry.py`, docs/deployment.md). Training draws d in 0..max_delay per sample.
            0 (the default) is the paper's SDP: a chunk starts right after its observation.
        sampling: how each executed chunk is sampled. "stream" (SDP, the default): one streaming
            step on the buffer carried over from the last chunk, N / h denoiser calls. Two diagnostics,
            for evaluating where a policy loses (e.g. `lerobot-eval --policy.sampling=full_denoise`):
            "fresh": every chunk sampled afresh from its own observation (the buffer dropped, primed by
            a full denoise, then one streaming step: N + N / h calls); "full_denoise": every chunk
            sampled as Diffusion Policy samples (one N-step denoise with every slot at one level, no
            buffer: N calls). Neither takes committed actions.
        init_from: warm start from a trained LeRobot `diffusion` checkpoint (a local `pretrained_model`
            folder or a Hub id): its matching weights and normaliser statistics are copied when the
            policy is built (`warm_start.py`). Ignored when an SDP checkpoint is loaded.
        optimizer_fused: LeRobot's Adam preset built with torch's fused kernel (`FusedAdamConfig`, the
            default); false builds LeRobot's own AdamConfig, the same update up to float rounding.
    Everything else means what it means in LeRobot's DiffusionConfig.
    """

    # Geometry
    n_obs_steps: int = 2
    n_action_steps: int = 8
    n_chunks: int = 2

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )

    # Vision encoder (LeRobot DP's fields; offline-safe: no pretrained download, GroupNorm).
    vision_backbone: str = "resnet18"
    resize_shape: tuple[int, int] | None = None
    crop_ratio: float = 1.0
    crop_shape: tuple[int, int] | None = (84, 84)
    crop_is_random: bool = True
    pretrained_backbone_weights: str | None = None
    use_group_norm: bool = True
    spatial_softmax_num_keypoints: int = 32
    use_separate_rgb_encoder_per_camera: bool = False

    # U-Net
    down_dims: tuple[int, ...] = (512, 1024, 2048)
    kernel_size: int = 5
    n_groups: int = 8
    diffusion_step_embed_dim: int = 128
    use_film_scale_modulation: bool = True
    gradient_checkpointing: bool = False
    step_conditioning: str = "flatten"

    # Noise scheduler
    noise_scheduler_type: str = "DDPM"
    num_train_timesteps: int = 100
    beta_schedule: str = "squaredcos_cap_v2"
    beta_start: float = 0.0001
    beta_end: float = 0.02
    prediction_type: str = "epsilon"
    clip_sample: bool = True
    clip_sample_range: float = 1.0
    num_inference_steps: int | None = None

    # SDP
    action_primer: str = "zero"
    noise_schemes: NoiseSchemeWeights = field(default_factory=NoiseSchemeWeights)
    chunkwise_grid: str = "sampler"
    noise_curriculum: NoiseCurriculum = field(default_factory=NoiseCurriculum)
    min_snr_gamma: float | None = 5.0
    # As LeRobot's DP: copy-padded actions past an episode's end stay in the loss (the policy learns
    # to hold the final pose). Masking them made no measurable difference (docs/results.md).
    do_mask_loss_for_padding: bool = False
    max_delay: int = 0
    sampling: str = "stream"

    # EMA (the authors' settings)
    use_ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999

    compile_model: bool = False
    compile_mode: str = "reduce-overhead"

    # Warm start from a LeRobot Diffusion Policy checkpoint (path or Hub id)
    init_from: str | None = None

    # Training presets
    optimizer_lr: float = 1e-4
    optimizer_betas: tuple = (0.95, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-6
    optimizer_fused: bool = True  # torch's fused Adam kernel (FusedAdamConfig); false: LeRobot's Adam
    scheduler_name: str = "cosine"
    scheduler_warmup_steps: int = 500

    push_to_hub: bool = False

    def __post_init__(self):
        super().__post_init__()
        try:
            self._validate()
        except ValueError as e:
            # draccus replaces the reason with "Couldn't instantiate class SDPConfig": say it first.
            logging.error("Invalid SDP config: %s", e)
            raise

    def _validate(self) -> None:
        if not self.vision_backbone.startswith("resnet"):
            raise ValueError(f"`vision_backbone` must be a ResNet variant, got {self.vision_backbone!r}.")
        _check_choice("prediction_type", self.prediction_type, ("epsilon", "sample"))
        _check_choice("noise_scheduler_type", self.noise_scheduler_type, ("DDPM", "DDIM"))
        _check_choice("action_primer", self.action_primer, ACTION_PRIMERS)
        _check_choice("step_conditioning", self.step_conditioning, STEP_CONDITIONINGS)
        _check_choice("sampling", self.sampling, SAMPLINGS)
        _check_choice("chunkwise_grid", self.chunkwise_grid, CHUNKWISE_GRIDS)
        if isinstance(self.noise_schemes, dict):  # convenience for Python callers
            self.noise_schemes = NoiseSchemeWeights(**self.noise_schemes)
        if isinstance(self.noise_curriculum, dict):
            self.noise_curriculum = NoiseCurriculum(**self.noise_curriculum)
        if self.chunkwise_grid == "training_table" and self.num_train_timesteps % self.n_chunks:
            raise ValueError(
                f"chunkwise_grid='training_table' splits the {self.num_train_timesteps} training timesteps "
                f"into n_chunks={self.n_chunks} equal bands: make `num_train_timesteps` a multiple of "
                "`n_chunks`, or use `--policy.chunkwise_grid=sampler`."
            )
        if self.min_snr_gamma is not None and not self.min_snr_gamma > 0:
            raise ValueError(
                f"`min_snr_gamma` must be positive (e.g. 5.0) or null for no weighting, got "
                f"{self.min_snr_gamma}."
            )
        if self.num_inference_steps is not None and self.num_inference_steps > self.num_train_timesteps:
            raise ValueError(
                f"num_inference_steps={self.num_inference_steps} > num_train_timesteps="
                f"{self.num_train_timesteps}: lower `num_inference_steps`."
            )
        if not (0 < self.crop_ratio <= 1.0):
            raise ValueError(f"`crop_ratio` must be in (0, 1], got {self.crop_ratio}.")
        if self.resize_shape is not None:
            ratio = self.crop_ratio
            self.crop_shape = None if ratio == 1.0 else tuple(int(d * ratio) for d in self.resize_shape)
        if self.crop_shape is not None and min(self.crop_shape) <= 0:
            raise ValueError(f"`crop_shape` must have positive dimensions, got {self.crop_shape}.")
        if not 0.0 <= self.ema_max_decay < 1.0 or self.ema_power <= 0:
            raise ValueError("EMA needs 0 <= ema_max_decay < 1 and ema_power > 0.")
        logging.info("%s.", self.geometry.describe())  # building the geometry validates the sizes

    @property
    def inference_steps(self) -> int:
        """N, the denoising steps for a full trajectory (defaults to num_train_timesteps, as DP)."""
        return self.num_inference_steps or self.num_train_timesteps

    @property
    def geometry(self) -> ChunkGeometry:
        if not self.down_dims:
            raise ValueError("`down_dims` must list at least one U-Net level.")
        return ChunkGeometry(
            n_obs_steps=self.n_obs_steps,
            chunk_len=self.n_action_steps,
            n_chunks=self.n_chunks,
            num_inference_steps=self.inference_steps,
            downsampling=2 ** (len(self.down_dims) - 1),
            max_delay=self.max_delay,
        )

    @property
    def horizon(self) -> int:
        return self.geometry.horizon

    @property
    def drop_n_last_frames(self) -> int:
        """Start frames LeRobot's EpisodeAwareSampler drops at each episode's end: exactly those whose
        executed chunk would run past it. The current frame sits at slot To-1 (the first executed
        slot), so the executed chunk reaches frame t + Tb - 1; every later slot may run past the end
        and is copy-padded by the dataset (`action_is_pad`). With this, every frame of an episode is
        executed in some training sample, at any h (DP's field is 7: the same at Tb = 8)."""
        g = self.geometry
        return g.executed.stop - 1 - g.n_past

    def get_optimizer_preset(self) -> AdamConfig:
        adam = FusedAdamConfig if self.optimizer_fused else AdamConfig
        return adam(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
        )

    def get_scheduler_preset(self) -> DiffuserSchedulerConfig:
        return DiffuserSchedulerConfig(name=self.scheduler_name, num_warmup_steps=self.scheduler_warmup_steps)

    def validate_features(self) -> None:
        if self.robot_state_feature is None:
            raise ValueError(
                "SDP needs `observation.state` among the input features (the robot's proprioception)."
            )
        if self.action_feature is None:
            raise ValueError("SDP needs an `action` output feature.")
        if not self.image_features and self.env_state_feature is None:
            raise ValueError(
                "SDP needs at least one camera (`observation.image*`) or `observation.environment_state` "
                "as input."
            )
        shapes = {key: tuple(ft.shape) for key, ft in self.image_features.items()}
        if len(set(shapes.values())) > 1:
            raise ValueError(f"All camera images must share one shape, got {shapes}.")
        if self.resize_shape is None and self.crop_shape is not None:
            for key, shape in shapes.items():
                if self.crop_shape[0] > shape[1] or self.crop_shape[1] > shape[2]:
                    raise ValueError(
                        f"`crop_shape` {tuple(self.crop_shape)} does not fit `{key}` of shape {shape}: "
                        "set `--policy.crop_shape` to at most the image size (or null for no crop)."
                    )
        if self.action_primer == "constant" and self.robot_state_feature.shape != self.action_feature.shape:
            raise ValueError(
                f"action_primer='constant' repeats the current state as the first actions, but "
                f"observation.state has shape {tuple(self.robot_state_feature.shape)} and action "
                f"{tuple(self.action_feature.shape)}: they are not one space. "
                "Use `--policy.action_primer=zero`."
            )

    @property
    def observation_delta_indices(self) -> list:
        return list(range(1 - self.n_obs_steps, 1))

    @property
    def action_delta_indices(self) -> list:
        return list(range(1 - self.n_obs_steps, 1 - self.n_obs_steps + self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None
