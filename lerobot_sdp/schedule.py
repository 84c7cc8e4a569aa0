"""Per-slot diffusion schedule maths: forward noising and DDPM / DDIM reverse steps where every slot
of the action sequence carries its own noise level.

Paper Eq. 2: ``A^{k-1} <- alpha_k (A^k - gamma_k eps_theta(A^k; O, k) + N(0, sigma_k^2))`` with the
coefficients gathered per slot. The coefficients are those of diffusers' ``DDPMScheduler.step`` and
``DDIMScheduler.step`` (eta = 0), computed from the scheduler's own ``alphas_cumprod`` so that, with
every slot at one level, one step here equals one diffusers step (tests/test_schedule.py).

Levels live in two units (docs/algorithm.md, section 3): ``k`` = denoising steps remaining
(0 = clean, N = pure noise) and ``t`` = training timestep fed to the network. ``train_timesteps``
is the single map between them: the table diffusers' ``set_timesteps(N)`` builds, with
``k = 0 -> t = -1`` meaning "clean".
"""

from typing import NamedTuple

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from torch import Tensor, nn

CLEAN = -1  # the training timestep of a clean slot (k = 0)


class PerSlotSchedule(nn.Module):
    """Schedule tables as non-persistent buffers, so they follow ``.to(device)`` and stay out of
    checkpoints (they are rebuilt from the config)."""

    def __init__(self, scheduler: DDPMScheduler | DDIMScheduler, num_inference_steps: int):
        super().__init__()
        if not isinstance(scheduler, DDPMScheduler | DDIMScheduler):
            raise TypeError(f"Expected a diffusers DDPMScheduler or DDIMScheduler, got {type(scheduler)}.")
        cfg = scheduler.config
        if num_inference_steps > cfg.num_train_timesteps:
            raise ValueError(
                f"num_inference_steps={num_inference_steps} exceeds num_train_timesteps="
                f"{cfg.num_train_timesteps}. Lower `num_inference_steps`."
            )
        self.is_ddim = isinstance(scheduler, DDIMScheduler)
        self.prediction_type = cfg.prediction_type
        self.clip_range = cfg.clip_sample_range if cfg.clip_sample else None
        self.num_train_timesteps = cfg.num_train_timesteps
        scheduler.set_timesteps(num_inference_steps)
        timesteps = torch.as_tensor(scheduler.timesteps, dtype=torch.long).flip(0)  # ascending
        self.register_buffer(
            "timestep_table", torch.cat([torch.tensor([CLEAN]), timesteps]), persistent=False
        )
        # diffusers uses 1 (DDPM) or final_alpha_cumprod (DDIM) once the previous timestep is negative.
        final = float(scheduler.final_alpha_cumprod) if self.is_ddim else 1.0
        abar = scheduler.alphas_cumprod.to(torch.float32)
        # Index t + 1, so that t = -1 ("clean / before the first step") reads `final`.
        self.register_buffer("abar_shifted", torch.cat([torch.tensor([final]), abar]), persistent=False)

    def train_timesteps(self, k: Tensor) -> Tensor:
        """Steps remaining -> training timestep (-1 for k = 0). Shared by DDPM, DDIM and training."""
        return self.timestep_table[k]

    def alpha_bar(self, t: Tensor) -> Tensor:
        """abar_t per slot, (..., T) -> (..., T, 1); t = -1 gives the clean-end value."""
        return self.abar_shifted[t + 1].unsqueeze(-1)

    def add_noise(self, x0: Tensor, eps: Tensor, t: Tensor) -> Tensor:
        """Forward process q(x_t | x_0) per slot: sqrt(abar_t) x0 + sqrt(1 - abar_t) eps."""
        abar = self.alpha_bar(t)
        return abar.sqrt() * x0 + (1 - abar).sqrt() * eps

    def coefficients(self, k: Tensor, all_active: bool | None = None) -> "StepCoefficients":
        """Gather every per-slot coefficient of one reverse step from steps-remaining ``k`` (..., T).

        A streaming call visits the same s level patterns every time, so callers compute these once
        and reuse them: a step is then a handful of tensor ops (the buffer's bookkeeping budget).
        ``active`` is None when every slot steps (always, while streaming), so that the step skips its
        ``torch.where``; a caller that knows (``all_active``) spares the read of ``k``."""
        t, t_prev = self.train_timesteps(k), self.train_timesteps((k - 1).clamp(min=0))
        abar, abar_prev = self.alpha_bar(t), self.alpha_bar(t_prev)
        active = (k > 0).unsqueeze(-1)
        if all_active is None:
            all_active = bool(active.all())
        common = dict(
            timesteps=t,
            active=None if all_active else active,
            sqrt_abar=abar.sqrt(),
            sqrt_one_minus_abar=(1 - abar).sqrt(),
        )
        if self.is_ddim:
            return StepCoefficients(**common, **ddim_coefficients(abar, abar_prev))
        return StepCoefficients(**common, **ddpm_coefficients(abar, abar_prev, t))

    def apply_step(
        self,
        c: "StepCoefficients",
        model_output: Tensor,
        sample: Tensor,
        noise: Tensor | None = None,
    ) -> Tensor:
        """x_t -> x_{t_prev} for every slot with k > 0; slots with k = 0 are left untouched
        (indexing abar at k = 0 would silently wrap to the noisiest level). DDPM's step noise is
        ``noise`` when given (the streaming buffer draws it up front), else the global RNG's."""
        if self.prediction_type == "epsilon":
            eps = model_output
            x0 = (sample - c.sqrt_one_minus_abar * eps) / c.sqrt_abar
        else:  # "sample"; diffusers derives epsilon from the unclipped x0
            x0 = model_output
            eps = (sample - c.sqrt_abar * x0) / c.sqrt_one_minus_abar
        if self.clip_range is not None:
            x0 = x0.clamp(-self.clip_range, self.clip_range)
        prev = c.x0_coef * x0
        if c.xt_coef is not None:
            prev = prev + c.xt_coef * sample
        if c.eps_coef is not None:
            prev = prev + c.eps_coef * eps
        if c.noise_std is not None:
            prev = prev + c.noise_std * (torch.randn_like(sample) if noise is None else noise)
        return prev if c.active is None else torch.where(c.active, prev, sample)

    def step(self, model_output: Tensor, k: Tensor, sample: Tensor, noise: Tensor | None = None) -> Tensor:
        """One reverse step from per-slot steps-remaining ``k`` (B, T)."""
        return self.apply_step(self.coefficients(k), model_output, sample, noise)


def gaussian_like(x: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """N(0, I) of ``x``'s shape, device and dtype; every draw of a streaming call goes through here so
    that one ``generator`` reproduces the whole stream (``randn_like`` takes no generator)."""
    return torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)


class StepCoefficients(NamedTuple):
    """Per-slot coefficients of one reverse step, shape (..., T, 1) (timesteps: (..., T)).
    prev = x0_coef * x0 + xt_coef * x_t + eps_coef * eps + noise_std * z, unused terms None;
    ``active`` (slots with k > 0) is None when every slot steps."""

    timesteps: Tensor
    active: Tensor | None
    sqrt_abar: Tensor
    sqrt_one_minus_abar: Tensor
    x0_coef: Tensor
    xt_coef: Tensor | None
    eps_coef: Tensor | None
    noise_std: Tensor | None


def ddpm_coefficients(abar: Tensor, abar_prev: Tensor, t: Tensor) -> dict:
    """DDPM posterior q(x_{t_prev} | x_t, x0) (Ho et al. Eq. 7, diffusers DDPMScheduler.step with
    variance "fixed_small"); diffusers adds no noise on the step from t = 0."""
    beta_t = 1 - abar / abar_prev
    variance = ((1 - abar_prev) / (1 - abar) * beta_t).clamp(min=1e-20)
    return dict(
        x0_coef=abar_prev.sqrt() * beta_t / (1 - abar),
        xt_coef=(1 - beta_t).sqrt() * (1 - abar_prev) / (1 - abar),
        eps_coef=None,
        noise_std=variance.sqrt() * (t > 0).unsqueeze(-1),
    )


def ddim_coefficients(abar: Tensor, abar_prev: Tensor) -> dict:
    """Deterministic DDIM (Song et al. Eq. 12 with eta = 0, diffusers DDIMScheduler.step)."""
    return dict(x0_coef=abar_prev.sqrt(), xt_coef=None, eps_coef=(1 - abar_prev).sqrt(), noise_std=None)
