"""Per-slot diffusion schedule maths: forward noising and DDPM / DDIM reverse steps where every slot
of the action sequence carries its own noise level.

Paper Eq. 2: ``A^{k-1} <- alpha_k (A^k - gamma_k eps_theta(A^k; O, k) + N(0, sigma_k^2))`` with the
coefficients gathered per slot. The coefficients are those of diffusers' ``DDPMScheduler.step`` and
``DDIMScheduler.step`` (eta = 0), computed from the scheduler's own ``alphas_cumprod`` so that, with
every slot at one level, one step here equals one diffusers step (tests/test_schedule.py).

Levels live in two units (sdp-algorithm.md, section 3): ``k`` = denoising steps remaining
(0 = clean, N = pure noise) and ``t`` = training timestep fed to the network. ``train_timesteps``
is the single map between them: the table diffusers' ``set_timesteps(N)`` builds, with
``k = 0 -> t = -1`` meaning "clean".
"""

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from torch import Tensor, nn


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
        self.num_inference_steps = num_inference_steps
        scheduler.set_timesteps(num_inference_steps)
        timesteps = torch.as_tensor(scheduler.timesteps, dtype=torch.long).flip(0)  # ascending
        self.register_buffer("timestep_table", torch.cat([torch.tensor([-1]), timesteps]), persistent=False)
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

    def _x0_and_eps(self, model_output: Tensor, sample: Tensor, abar: Tensor) -> tuple[Tensor, Tensor]:
        if self.prediction_type == "epsilon":
            x0 = (sample - (1 - abar).sqrt() * model_output) / abar.sqrt()
            return x0, model_output
        x0 = model_output  # "sample" prediction
        return x0, (sample - abar.sqrt() * x0) / (1 - abar).sqrt()

    def _clip(self, x0: Tensor) -> Tensor:
        return x0 if self.clip_range is None else x0.clamp(-self.clip_range, self.clip_range)

    def ddpm_step(self, model_output: Tensor, k: Tensor, sample: Tensor, noise: Tensor) -> Tensor:
        """One DDPM reverse step per slot (diffusers DDPMScheduler.step, variance "fixed_small")."""
        t, t_prev = self.train_timesteps(k), self.train_timesteps((k - 1).clamp(min=0))
        abar, abar_prev = self.alpha_bar(t), self.alpha_bar(t_prev)
        beta_t = 1 - abar / abar_prev
        x0, _ = self._x0_and_eps(model_output, sample, abar)
        x0 = self._clip(x0)
        mean = (abar_prev.sqrt() * beta_t / (1 - abar)) * x0 + ((1 - beta_t).sqrt() * (1 - abar_prev) / (1 - abar)) * sample
        variance = ((1 - abar_prev) / (1 - abar) * beta_t).clamp(min=1e-20)
        # diffusers adds no noise on the step from t = 0.
        return mean + (t > 0).unsqueeze(-1) * variance.sqrt() * noise

    def ddim_step(self, model_output: Tensor, k: Tensor, sample: Tensor) -> Tensor:
        """One deterministic DDIM reverse step per slot (diffusers DDIMScheduler.step, eta = 0)."""
        t, t_prev = self.train_timesteps(k), self.train_timesteps((k - 1).clamp(min=0))
        abar, abar_prev = self.alpha_bar(t), self.alpha_bar(t_prev)
        x0, eps = self._x0_and_eps(model_output, sample, abar)
        x0 = self._clip(x0)
        return abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps

    def step(self, model_output: Tensor, k: Tensor, sample: Tensor, noise: Tensor | None = None) -> Tensor:
        """Move every slot with k > 0 one step towards clean; slots with k = 0 are left untouched
        (indexing abar at k = 0 would silently wrap to the noisiest level)."""
        if self.is_ddim:
            stepped = self.ddim_step(model_output, k, sample)
        else:
            stepped = self.ddpm_step(model_output, k, sample, torch.randn_like(sample) if noise is None else noise)
        return torch.where((k > 0).unsqueeze(-1), stepped, sample)
