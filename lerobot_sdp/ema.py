"""Exponential moving average of the weights, as the SDP and Diffusion Policy authors trained with.

The decay follows diffusers' ``EMAModel.get_decay`` with warm-up (inv_gamma = 1):
``decay = min(max_decay, 1 - (1 + step) ** -power)``, the schedule of the authors' configs
(power 0.75, max 0.9999). The averaged copy is a registered sub-module of the policy, so it is saved
in model.safetensors next to the raw weights and a resumed run continues the same average.
"""

import torch
from torch import Tensor, nn


def ema_decay(step: Tensor, power: float, max_decay: float) -> Tensor:
    """The decay at optimiser step ``step`` (a 0-d tensor on the model's device: no host read)."""
    return (1.0 - (1.0 + step.float()) ** -power).clamp(0.0, max_decay)


@torch.no_grad()
def ema_update(averaged: nn.Module, model: nn.Module, decay: Tensor) -> None:
    """averaged <- decay * averaged + (1 - decay) * model for parameters; buffers are copied."""
    avg = list(averaged.parameters())
    new = [p.detach() for p in model.parameters()]
    # avg += (1 - decay) (new - avg) in one fused multi-tensor pass (lerp), the weight a 0-d tensor
    # left on the device (no host read): 3 tensor reads and writes per weight instead of sub, mul and add's 8
    weight = (1.0 - decay).to(avg[0].dtype)
    torch._foreach_lerp_(avg, new, [weight] * len(avg))
    for b_avg, b_new in zip(averaged.buffers(), model.buffers(), strict=True):
        b_avg.copy_(b_new)
