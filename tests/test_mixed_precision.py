"""SDP under autocast (`--policy.use_amp=true`, bf16 on CPU): the U-Net runs in bf16, the schedule
maths (x0, clipping, the step, the streaming buffer) stays float32, and a streamed chunk stays within
a stated tolerance of float32's."""

import pytest
import torch
from sdp_test_utils import history, tiny_config

from lerobot_sdp import SDPPolicy
from lerobot_sdp.schedule import PerSlotSchedule

# bf16 keeps 8 bits of mantissa: each U-Net output is off by ~0.4 % of its size. Measured over the
# 4 chunks of a stream: at most 0.005 on this test's fitted tiny model, 0.011 on the Push-T main
# job's checkpoint (normalised actions in [-1, 1]). An untrained network amplifies the same
# rounding up to 0.13 (its denoising does not contract), so the model is fitted first.
CHUNK_ATOL = 0.02


def autocast(on: bool):
    return torch.autocast("cpu", dtype=torch.bfloat16, enabled=on)


def fitted_policy(prediction_type: str) -> SDPPolicy:
    """A tiny SDP fitted for 150 steps to actions that follow the state (a ramp around it)."""
    torch.manual_seed(0)
    cfg = tiny_config(prediction_type=prediction_type, use_ema=False)
    policy = SDPPolicy(cfg)
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=3e-3)
    ramp = torch.linspace(-0.5, 0.5, cfg.geometry.horizon)[None, :, None]
    for _ in range(150):
        batch = history(cfg, batch_size=16)
        batch["action"] = batch["observation.state"][:, -1:] - 0.5 + ramp
        optimizer.zero_grad()
        policy.forward(batch)[0].backward()
        optimizer.step()
    return policy.eval()


def streamed_chunks(policy: SDPPolicy, bf16: bool, n: int = 4) -> list[torch.Tensor]:
    """`n` chunks of one stream (primer, then streaming calls) on one observation, every draw from
    one seeded generator."""
    policy.reset()
    torch.manual_seed(7)
    obs = history(policy.config, batch_size=2)
    gen = torch.Generator().manual_seed(0)
    with autocast(bf16), torch.no_grad():
        return [policy.predict_action_chunk(obs, generator=gen) for _ in range(n)]


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_a_streamed_chunk_under_bf16_autocast_matches_float32(prediction_type, monkeypatch):
    policy = fitted_policy(prediction_type)
    seen = []
    apply_step = PerSlotSchedule.apply_step

    def recording_step(schedule, c, model_output, sample, noise=None):
        seen.append((model_output.dtype, sample.dtype))
        return apply_step(schedule, c, model_output, sample, noise)

    reference = streamed_chunks(policy, bf16=False)
    monkeypatch.setattr(PerSlotSchedule, "apply_step", recording_step)
    mixed = streamed_chunks(policy, bf16=True)
    assert seen and set(seen) == {(torch.float32, torch.float32)}  # the step never sees bf16
    assert policy._buffer.sample.dtype == torch.float32
    for ref, got in zip(reference, mixed, strict=True):
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, ref, atol=CHUNK_ATOL, rtol=0)
    assert not all(torch.equal(r, g) for r, g in zip(reference, mixed, strict=True))  # bf16 really ran


def test_the_training_loss_under_bf16_autocast_is_float32_and_close():
    torch.manual_seed(0)
    cfg = tiny_config(max_delay=1)
    policy = SDPPolicy(cfg).train()
    gen = torch.Generator().manual_seed(1)
    batch = {
        k: torch.rand((4, cfg.n_obs_steps, *ft.shape), generator=gen) for k, ft in cfg.input_features.items()
    }
    batch["action"] = torch.rand((4, cfg.geometry.horizon, 2), generator=gen) * 2 - 1
    losses = []
    for bf16 in (False, True):
        torch.manual_seed(2)
        with autocast(bf16):
            loss = policy.forward(batch)[0]
        loss.backward()
        assert loss.dtype == torch.float32
        assert all(
            p.grad.dtype == torch.float32 and p.grad.isfinite().all() for p in policy.get_optim_params()
        )
        policy.zero_grad()
        losses.append(float(loss.detach()))
    assert losses[0] != losses[1]
    assert abs(losses[1] - losses[0]) < 0.02 * losses[0]
