"""Streaming Diffusion Policy (paper: Høeg, Du, Egeland, "Fast Policy Synthesis with Variable Noise
Diffusion Models", arXiv 2406.04806; the paper's Algorithm 1 is `SDPPolicy.predict_action_chunk`).

`SDPModel` owns the maths. It reuses LeRobot Diffusion Policy's observation encoders and U-Net
(`DiffusionModel`) and replaces what per-slot noise levels change: the U-Net's step encoder
(`unet.py`), the loss (`noise_schemes.py`, paper Eq. 5), sampling (`schedule.py`, paper Eq. 2), the
action primers and one streaming step (`buffer.py`). `SDPPolicy` is LeRobot's interface to it: the
observation and action queues, the stream (`StreamingBuffer`), EMA, checkpoints; what it accepts as
input is checked in `observations.py`, and LeRobot's RTC engine is read in `rtc.py`.
"""

import copy
import logging
from collections import deque
from contextvars import ContextVar

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import get_dtype_from_parameters, populate_queues
from lerobot.processor import NormalizerProcessorStep, TransitionKey, UnnormalizerProcessorStep
from lerobot.processor.converters import create_transition
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from safetensors import safe_open
from torch import Tensor

from .buffer import (
    Denoiser,
    StreamingBuffer,
    StreamNoise,
    reverse_plan,
    run_reverse_steps,
    step_noise,
    stream_step,
)
from .configuration_sdp import SDPConfig
from .data_parallel import rank_generator
from .ema import ema_decay, ema_update
from .loss_weighting import min_snr_weights
from .model_card import add_introduction
from .noise_schemes import sample_delays, sample_levels
from .observations import (
    check_observation,
    finite_flags,
    offline_history,
    refuse_non_finite,
    reject_unknown_kwargs,
    repeated_frame,
    stack_cameras,
)
from .rtc import committed_under_rtc, engine_problem, engine_result, rest_of_last_chunk
from .schedule import PerSlotSchedule, StepCoefficients, gaussian_like
from .unet import make_variable_noise, plan_embedding_cache
from .warm_start import WarmStartReport, merged_stats, warm_start

# Set while `SDPPolicy.from_pretrained` builds the policy: the checkpoint's weights replace the warm
# start's, and the Diffusion Policy checkpoint it named may no longer be reachable.
_LOADING_CHECKPOINT: ContextVar[bool] = ContextVar("sdp_loading_checkpoint", default=False)
_UNSET = object()  # the training noise stream is chosen at the first training step


class SDPModel(DiffusionModel):
    """DP's observation encoders and U-Net, trained and sampled with one noise level per slot."""

    def __init__(self, config: SDPConfig):
        super().__init__(config)
        # DP compiles the U-Net module in place under `compile_model`, which renames every weight
        # (`unet._orig_mod.`); SDP compiles its whole streaming step instead (`stream_step_for`),
        # so checkpoints load the same with and without compilation.
        self.unet = getattr(self.unet, "_orig_mod", self.unet)
        self.geometry = config.geometry
        make_variable_noise(
            self.unet, config.diffusion_step_embed_dim, self.geometry.horizon, config.step_conditioning
        )
        self.schedule = PerSlotSchedule(self.noise_scheduler, self.num_inference_steps)
        self._compiled_stream = None

    def global_conditioning(self, history: dict[str, Tensor]) -> Tensor:
        """DP's observation conditioning of a (B, n_obs_steps, ...) history (LeRobot's encoders)."""
        return self._prepare_global_conditioning(history)

    def primer(
        self,
        history: dict[str, Tensor],
        state_to_action: Tensor,
        generator: torch.Generator | None,
        kind: str | None = None,
    ) -> Tensor:
        """Clean (normalised) sequence a new stream starts from (paper Sec. "Initializing the buffer"):
        zeros, the newest state repeated as actions (`state_to_action`: scale and offset), or a full
        denoise; ``kind`` overrides `action_primer`. Only "denoise" needs the observation conditioning."""
        state = history[OBS_STATE]
        batch_size = state.shape[0]
        shape = (batch_size, self.geometry.horizon, self.config.action_feature.shape[0])
        primer = kind or self.config.action_primer
        if primer == "denoise":
            return self.conditional_sample(batch_size, self.global_conditioning(history), generator)
        if primer == "constant":
            if torch.isnan(state_to_action).any():
                raise ValueError(
                    "action_primer='constant' needs the dataset statistics of observation.state and "
                    "action, and this policy was built without them (or its state and action spaces "
                    "differ). Use `--policy.action_primer=zero`."
                )
            scale, offset = state_to_action
            current = history[OBS_STATE][:, -1] * scale + offset  # the newest observation
            return current.unsqueeze(1).expand(shape).contiguous()
        return torch.zeros(shape, device=state.device, dtype=state.dtype)

    def denoiser(self, global_cond: Tensor) -> Denoiser:
        """The U-Net at per-slot timesteps, its output in the sample's dtype: under autocast the
        network runs in bf16 / fp16 while the schedule maths (x0, clipping, the step) stays float32."""

        def denoise(sample: Tensor, timesteps: Tensor) -> Tensor:
            return self.unet(sample, timesteps, global_cond=global_cond).to(sample.dtype)

        return denoise

    def cache_step_embeddings(self, plan: list[StepCoefficients]) -> None:
        """Let the step encoder keep the embeddings of this streaming plan (`unet.PlanEmbeddingCache`)."""
        encoder = self.unet.diffusion_step_encoder
        plan_embedding_cache(encoder).keep(encoder, [c.timesteps for c in plan])

    def stream_step(
        self,
        history: dict[str, Tensor],
        window: Tensor,
        plan: list[StepCoefficients],
        noise: StreamNoise,
        committed: int = 0,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Everything one streaming call computes: the observation conditioning, s denoiser calls and
        the shift (`buffer.stream_step`), plus one finite flag per observation key, read by the caller
        after the call so that checking costs no host sync inside it. Compiled as one graph with
        `compile_model` (one graph per number of committed slots)."""
        finite = finite_flags(history)
        global_cond = self.global_conditioning(history)
        chunk, next_sample = stream_step(
            self.schedule, self.geometry, self.denoiser(global_cond), window, plan, noise, committed
        )
        return chunk, next_sample, finite

    def stream_step_for(self, device: torch.device, compiled: bool):
        """`stream_step` as it runs on ``device``: plain, or compiled as one graph with no breaks. On
        CUDA, "reduce-overhead" captures the call as a CUDA graph; elsewhere that mode falls back to
        "default"."""
        if not compiled:
            return self.stream_step
        mode = self.compile_mode(device)
        if self._compiled_stream is None:
            self._compiled_stream = torch.compile(self.stream_step, mode=mode, fullgraph=True, dynamic=False)
        if mode != "reduce-overhead":
            return self._compiled_stream

        def replay(*args):
            # a CUDA graph's outputs are overwritten by its next replay: keep copies
            torch.compiler.cudagraph_mark_step_begin()
            return tuple(out.clone() for out in self._compiled_stream(*args))

        return replay

    def compile_mode(self, device: torch.device) -> str:
        """`compile_mode`, except that "reduce-overhead" (CUDA graphs) falls back to "default" off CUDA."""
        mode = self.config.compile_mode
        return "default" if mode == "reduce-overhead" and device.type != "cuda" else mode

    def conditional_sample(
        self,
        batch_size: int,
        global_cond: Tensor,
        generator: torch.Generator | None = None,
        noise: Tensor | None = None,
    ) -> Tensor:
        """Full N-step denoise with every slot at one level: DP-style sampling, SDP's "denoise" primer,
        and DP's `generate_actions` (which passes its initial sample as `noise`)."""
        shape = (batch_size, self.geometry.horizon, self.config.action_feature.shape[0])
        if noise is not None and tuple(noise.shape) != shape:
            raise ValueError(f"noise has shape {tuple(noise.shape)}; SDP's initial sample is {shape}.")
        sample = (
            noise
            if noise is not None
            # the weights' dtype, as LeRobot's DP: under autocast the conditioning may be bf16
            else torch.randn(
                shape,
                generator=generator,
                device=global_cond.device,
                dtype=get_dtype_from_parameters(self.unet),
            )
        )
        n = self.num_inference_steps
        k_start = torch.full((self.geometry.horizon,), n, device=sample.device)
        plan = reverse_plan(self.schedule, k_start, n, batch_size)
        noise = step_noise(plan, sample, generator)
        return run_reverse_steps(self.schedule, self.denoiser(global_cond), sample, plan, noise)

    def compute_loss(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None = None,
        step: Tensor | None = None,
    ) -> Tensor:
        """Paper Eq. 5: MSE between the noise (or clean actions) and the prediction, levels per slot,
        each slot Min-SNR weighted under `min_snr_gamma` (`loss_weighting.py`). ``step``: the
        optimiser steps taken (0-d, on the device), read by the noise curriculum only. Every random
        draw (levels, delays, noise) comes from ``generator``, the global RNG when None."""
        trajectory = batch[ACTION]
        if trajectory.shape[1] != self.geometry.horizon:
            raise ValueError(
                f"The batch holds {trajectory.shape[1]} action frames but SDP's horizon is "
                f"{self.geometry.horizon}: build the dataset with this config's action_delta_indices."
            )
        global_cond = self.global_conditioning(batch)
        levels, committed = self.training_levels(trajectory.shape[0], generator, step)
        eps = gaussian_like(trajectory, generator)
        return self.denoising_loss(batch, global_cond, levels, eps, committed)

    def training_levels(
        self, batch_size: int, generator: torch.Generator | None, step: Tensor | None
    ) -> tuple[Tensor, Tensor | None]:
        """(B, T) training timesteps of one batch (the mixture, the curriculum, the delays) and the
        committed slots the loss leaves out (None without `max_delay`)."""
        cfg = self.config
        curriculum = cfg.noise_curriculum
        if curriculum.enabled and step is None:
            raise ValueError("noise_curriculum needs the training step: pass `step` to compute_loss.")
        share = curriculum.constant_share(step) if curriculum.enabled else None
        levels = sample_levels(
            cfg.noise_schemes, batch_size, self.geometry, self.schedule, generator, cfg.chunkwise_grid, share
        )
        return sample_delays(levels, self.geometry, generator)

    def denoising_loss(
        self,
        batch: dict[str, Tensor],
        global_cond: Tensor,
        levels: Tensor,
        eps: Tensor,
        committed: Tensor | None = None,
    ) -> Tensor:
        """The loss of one batch at given per-slot ``levels`` (B, T) and noise ``eps``."""
        cfg = self.config
        trajectory = batch[ACTION]
        # committed slots (timestep -1) come out clean: abar is 1 there (DDPM, and DDIM's set_alpha_to_one)
        pred = self.denoiser(global_cond)(self.schedule.add_noise(trajectory, eps, levels), levels)
        target = eps if cfg.prediction_type == "epsilon" else trajectory
        loss = F.mse_loss(pred, target, reduction="none")
        if cfg.min_snr_gamma is not None:
            loss = loss * min_snr_weights(self.schedule, levels, cfg.min_snr_gamma, cfg.prediction_type)
        mask = None if committed is None else ~committed.unsqueeze(-1)  # committed slots are inputs only
        if cfg.do_mask_loss_for_padding and "action_is_pad" in batch:
            pad = (~batch["action_is_pad"]).unsqueeze(-1)
            mask = pad if mask is None else mask & pad
        if mask is None:
            return loss.mean()
        return (loss * mask).sum() / (mask.sum() * loss.shape[-1]).clamp_min(1)


def state_to_action_map(config: SDPConfig, dataset_stats: dict | None) -> Tensor:
    """(2, A) scale and offset taking a normalised state to the normalised action of the same raw
    value (the "constant" primer). NaN when the stats are unknown or the spaces differ.

    Computed with LeRobot's own normaliser steps (any normalisation mode they support): unnormalise
    the state, normalise it as an action. Both maps are affine per dimension, so probing them at 0
    and 1 gives the whole map, which is stored so that a checkpoint needs no statistics to prime."""
    action_dim = config.action_feature.shape[0]
    out = torch.full((2, action_dim), float("nan"))
    if not dataset_stats or OBS_STATE not in dataset_stats or ACTION not in dataset_stats:
        return out
    if tuple(config.robot_state_feature.shape) != (action_dim,):
        return out
    step_args = dict(
        features={OBS_STATE: config.robot_state_feature, ACTION: config.action_feature},
        norm_map=config.normalization_mapping,
        stats={key: dataset_stats[key] for key in (OBS_STATE, ACTION)},
    )
    probe = torch.stack([torch.zeros(action_dim), torch.ones(action_dim)])
    raw = UnnormalizerProcessorStep(**step_args)(create_transition(observation={OBS_STATE: probe}))
    as_action = NormalizerProcessorStep(**step_args)(
        create_transition(action=raw[TransitionKey.OBSERVATION][OBS_STATE])
    )[TransitionKey.ACTION]
    return torch.stack([as_action[1] - as_action[0], as_action[0]])


class SDPPolicy(PreTrainedPolicy):
    """Streaming Diffusion Policy: each executed chunk costs N / h denoiser calls instead of N."""

    config_class = SDPConfig
    name = "sdp"

    def __init__(self, config: SDPConfig, dataset_stats: dict | None = None, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.model = SDPModel(config)
        self.ema_model = copy.deepcopy(self.model).requires_grad_(False) if config.use_ema else None
        self.register_buffer("ema_step", torch.zeros((), dtype=torch.long))
        self.warm_start_report: WarmStartReport | None = None
        if config.init_from and not _LOADING_CHECKPOINT.get():
            self.warm_start_report = warm_start(self, config.init_from)
            checkpoint = self.warm_start_report.checkpoint  # the processor warns about the stats
            dataset_stats = merged_stats(checkpoint, dataset_stats, warn=False)
        self.register_buffer("state_to_action", state_to_action_map(config, dataset_stats))
        self.geometry = config.geometry
        # Plain attribute, not a registered buffer: streaming state never enters a checkpoint.
        self._buffer = StreamingBuffer(self.geometry, self.model.schedule)
        self._queues: dict[str, deque] = {}
        self._noise_stream: torch.Generator | object | None = _UNSET
        self.reset()

    def get_optim_params(self) -> dict:
        return self.model.parameters()

    def update(self) -> None:
        """Called by lerobot-train after every optimizer step: advance the EMA and the step count.
        `ema_step` counts optimiser steps with or without EMA (the noise curriculum reads it); it is
        saved in model.safetensors, so a resumed run (`--resume=true`) continues from its step."""
        if self.ema_model is not None:
            decay = ema_decay(self.ema_step, self.config.ema_power, self.config.ema_max_decay)
            ema_update(self.ema_model, self.model, decay)
        self.ema_step += 1  # on the device: no host read per training step

    def reset(self) -> None:
        """Drop the observation history, the queued actions and the streaming buffer."""
        cfg = self.config
        self._queues = {OBS_STATE: deque(maxlen=cfg.n_obs_steps), ACTION: deque(maxlen=cfg.n_action_steps)}
        if cfg.image_features:
            self._queues[OBS_IMAGES] = deque(maxlen=cfg.n_obs_steps)
        if cfg.env_state_feature:
            self._queues[OBS_ENV_STATE] = deque(maxlen=cfg.n_obs_steps)
        self._buffer.clear()

    def drop_queued_actions(self) -> None:
        """Drop the queued actions and the streaming buffer, keep the observation history: LeRobot's
        main branch calls this when the conditioning changes mid-episode (e.g. a new task), and the
        buffer's partly denoised future was computed under the old one. The next call re-primes."""
        self._queues[ACTION].clear()
        self._buffer.clear()

    def _sampling_model(self) -> SDPModel:
        return self.ema_model if self.ema_model is not None and not self.training else self.model

    @torch.no_grad()
    def select_action(
        self, batch: dict[str, Tensor], generator: torch.Generator | None = None, **kwargs
    ) -> Tensor:
        """Pop the next action; when the queue is empty run one streaming step (N/h denoiser calls).
        ``generator`` seeds every random draw of that step (same generator state, same actions)."""
        reject_unknown_kwargs("select_action", kwargs)
        # lerobot-eval's batch carries `action: None` (and may carry `task`): queue only the inputs
        batch = {k: v for k, v in batch.items() if k in self.config.input_features}
        check_observation(self.config, batch, time_axis=False)
        queued = self._queues[OBS_STATE]
        if queued and queued[-1].shape[0] != batch[OBS_STATE].shape[0]:
            logging.warning("SDP: the batch size changed without reset(); starting a new stream.")
            self.reset()
        if self._queues[ACTION]:  # between chunks the observation only joins the history
            self._queues = populate_queues(self._queues, stack_cameras(self.config, batch))
            return self._queues[ACTION].popleft()
        before = {key: queue.copy() for key, queue in self._queues.items()}
        self._queues = populate_queues(self._queues, stack_cameras(self.config, batch))
        try:
            chunk = self.predict_action_chunk(batch, generator=generator)
        except ValueError:  # a refused observation leaves the policy as it was
            self._queues = before
            raise
        self._queues[ACTION].extend(chunk.transpose(0, 1))
        return self._queues[ACTION].popleft()

    def supports_rtc(self) -> bool:
        """SDP runs under LeRobot's RTC engine (`lerobot-rollout --inference.type=rtc`), one streaming
        call per chunk: see `predict_action_chunk` and docs/deployment.md."""
        return True

    @torch.no_grad()
    def predict_action_chunk(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None = None,
        inference_delay: int | None = None,
        prev_chunk_left_over: Tensor | None = None,
        committed: int = 0,
        **kwargs,
    ) -> Tensor:
        """Algorithm 1, one iteration: s = N/h denoiser calls on the buffer, return the clean chunk
        (B, n_action_steps, A) and roll the buffer. The noisy tail stays internal.

        Online (after select_action filled the queues) the stacked history is used; offline, `batch`
        is a dataloader batch of (B, n_obs_steps, ...) observations (`_offline_history`).

        ``committed``: how many actions of the last chunk still run after this observation before the
        new chunk starts (the inference delay in control ticks, at most `max_delay`). They enter the
        denoised sequence as clean slots, so the chunk returned is the one that follows them. 0: the
        chunk starts right after the observation (the paper's SDP).

        From LeRobot's RTC engine (`inference_delay` / `prev_chunk_left_over` given), `batch` is one
        frame, and the result is the previous chunk's unexecuted actions followed by the new chunk
        (`_rtc_chunk`).

        Wrapped in `torch.compile` (`lerobot-rollout --use_torch_compile`), the buffer bookkeeping
        stays eager and the streaming step runs compiled, as with `compile_model`."""
        compiled = self.config.compile_model or torch.compiler.is_compiling()
        if inference_delay is not None or prev_chunk_left_over is not None:
            return self._rtc_chunk(batch, generator, compiled, prev_chunk_left_over, **kwargs)
        return self._predict_action_chunk(batch, generator, compiled, committed, **kwargs)

    @torch.compiler.disable
    def _predict_action_chunk(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None,
        compiled: bool,
        committed: int,
        **kwargs,
    ) -> Tensor:
        reject_unknown_kwargs("predict_action_chunk", kwargs)
        if self._queues[OBS_STATE]:
            history = {k: torch.stack(list(q), dim=1) for k, q in self._queues.items() if k != ACTION}
        else:
            history = offline_history(self.config, batch)
        return self._stream_step(history, generator, compiled, committed)

    @torch.compiler.disable
    def _rtc_chunk(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None,
        compiled: bool,
        left_over: Tensor | None,
        **kwargs,
    ) -> Tensor:
        """One RTC engine call (`rtc.py`): the frame repeated as the history; the action of the frame's
        tick and the rest of the last chunk committed when the policy was trained with `max_delay`;
        the result timed from the frame's tick (a slot for it, the rest, the new chunk)."""
        reject_unknown_kwargs("predict_action_chunk", kwargs)
        problem = engine_problem(self.config)
        if problem:
            raise ValueError(problem)
        history = repeated_frame(self.config, batch)
        rest = rest_of_last_chunk(self.config, left_over) if left_over is not None else None
        # the rest and the action before it end the buffer's last chunk unless the stream restarted
        streaming = rest is not None and self._buffer.last_chunk is not None
        committed = committed_under_rtc(len(rest)) if streaming and self.config.max_delay else 0
        chunk = self._stream_step(history, generator, compiled, committed)
        return engine_result(rest, chunk)

    def _stream_step(
        self,
        history: dict[str, Tensor],
        generator: torch.Generator | None,
        compiled: bool,
        committed: int = 0,
    ) -> Tensor:
        """One streaming call on a (B, n_obs_steps, ...) history, ``committed`` actions of the last
        chunk still to run before the new one: prime a new stream, run the step. The diagnostic
        `sampling` modes ("fresh", "full_denoise") sample the chunk without the last chunk's buffer."""
        batch_size = history[OBS_STATE].shape[0]
        sampling = self.config.sampling
        if sampling != "stream" and committed:
            raise ValueError(
                f"sampling={sampling!r} samples every chunk without the last one, so it cannot take "
                f"{committed} committed actions: use `--policy.sampling=stream` for delayed inference."
            )
        if self._buffer.batch_size not in (None, batch_size) or sampling == "fresh":
            self._buffer.clear()
        model = self._sampling_model()
        if sampling == "full_denoise":
            refuse_non_finite(history, finite_flags(history))
            actions = model.conditional_sample(batch_size, model.global_conditioning(history), generator)
            return actions[:, self.geometry.executed]
        generation = self._buffer.generation  # a reset() from another thread from here on wins
        fresh = self._buffer.sample is None
        if fresh:
            kind = "denoise" if sampling == "fresh" else None  # afresh: from this observation only
            primer = model.primer(history, self.state_to_action, generator, kind)
            self._buffer.prime(primer, generator, generation)
        model_step = model.stream_step_for(history[OBS_STATE].device, compiled)

        def step(
            window: Tensor, plan: list[StepCoefficients], noise: StreamNoise, committed: int
        ) -> tuple[Tensor, Tensor]:
            model.cache_step_embeddings(plan)
            chunk, next_sample, finite = model_step(history, window, plan, noise, committed)
            refuse_non_finite(history, finite)  # the one host read, after the chunk is computed
            return chunk, next_sample

        try:
            return self._buffer.stream_step(step, generator, committed, generation)
        except ValueError:
            if fresh:  # never keep a stream primed from a refused observation
                self._buffer.clear()
            raise

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, None]:
        """Training loss on a dataset batch of (B, n_obs_steps, ...) observations and (B, horizon, A)
        actions."""
        if self.config.image_features:
            batch = dict(batch)
            for key in self.config.image_features:
                if self.config.n_obs_steps == 1 and batch[key].ndim == 4:
                    batch[key] = batch[key].unsqueeze(1)
        batch = stack_cameras(self.config, batch)
        return self.model.compute_loss(batch, self._training_generator(), self.ema_step), None

    def _training_generator(self) -> torch.Generator | None:
        """This rank's stream of training noise under data parallelism, the global RNG (None) in one
        process (`data_parallel.rank_generator`); chosen at the first training step."""
        if self._noise_stream is _UNSET:
            self._noise_stream = rank_generator(self.ema_step.device)
        return self._noise_stream

    def generate_model_card(self, *args, **kwargs):
        """LeRobot's card, introduced as SDP (LeRobot's template only knows its built-in policies)."""
        return add_introduction(super().generate_model_card(*args, **kwargs))

    @classmethod
    def from_pretrained(cls, *args, **kwargs):
        """LeRobot's loader; a config's `init_from` (the warm start this policy began with) is not
        re-run: the checkpoint's trained weights are what is loaded."""
        token = _LOADING_CHECKPOINT.set(True)
        try:
            return super().from_pretrained(*args, **kwargs)
        finally:
            _LOADING_CHECKPOINT.reset(token)

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Refuse a checkpoint whose tensors do not fit the config (LeRobot loads non-strictly)."""
        expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        with safe_open(model_file, "pt") as f:
            found = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}  # noqa: SIM118 (not iterable)
        problems = [f"missing {k}" for k in expected.keys() - found.keys()]
        problems += [f"unexpected {k}" for k in found.keys() - expected.keys()]
        problems += [
            f"{k}: checkpoint {found[k]} vs config {expected[k]}"
            for k in expected.keys() & found.keys()
            if found[k] != expected[k]
        ]
        if problems:
            raise ValueError(
                f"The weights in {model_file} do not match their SDP config ({len(problems)} differences, "
                f"e.g. {'; '.join(sorted(problems)[:4])}). Shape-changing fields (n_obs_steps, "
                "n_action_steps, n_chunks, down_dims, diffusion_step_embed_dim, use_ema, ...) must stay as "
                "trained: restore the checkpoint's config.json or drop the conflicting --policy.* overrides."
            )
        return super()._load_as_safetensor(model, model_file, map_location, strict=True)
