"""Per-slot schedule maths against diffusers: with every slot at one level, one step must equal
DDPMScheduler.step / DDIMScheduler.step, and forward noising must equal add_noise."""

import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler

from lerobot_sdp.schedule import PerSlotSchedule

B, T, A = 3, 12, 2


def make(kind: str, prediction_type: str = "epsilon", clip: bool = True, n_train: int = 100):
    cls = DDPMScheduler if kind == "DDPM" else DDIMScheduler
    kwargs = dict(
        num_train_timesteps=n_train,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=clip,
        clip_sample_range=1.0,
        prediction_type=prediction_type,
    )
    return cls(**kwargs), cls(**kwargs)


@pytest.mark.parametrize("kind", ["DDPM", "DDIM"])
@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
@pytest.mark.parametrize("clip", [True, False])
@pytest.mark.parametrize("n_inference", [100, 10, 16])
def test_one_step_equals_diffusers(kind, prediction_type, clip, n_inference):
    ours_src, ref = make(kind, prediction_type, clip)
    schedule = PerSlotSchedule(ours_src, n_inference)
    ref.set_timesteps(n_inference)
    torch.manual_seed(0)
    sample = torch.randn(B, T, A)
    for i, t in enumerate(ref.timesteps):  # every step of a full reverse pass
        k = n_inference - i  # steps remaining before this step
        model_output = torch.randn(B, T, A)
        expected = ref.step(model_output, t, sample, generator=torch.Generator().manual_seed(i)).prev_sample
        noise = torch.randn(B, T, A, generator=torch.Generator().manual_seed(i))
        got = schedule.step(model_output, torch.full((B, T), k), sample, noise)
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
        assert int(schedule.train_timesteps(torch.tensor(k))) == int(t)
        sample = expected


@pytest.mark.parametrize("kind", ["DDPM", "DDIM"])
def test_add_noise_equals_diffusers(kind):
    ours_src, ref = make(kind)
    schedule = PerSlotSchedule(ours_src, 100)
    x0, eps = torch.randn(B, T, A), torch.randn(B, T, A)
    t = torch.randint(0, 100, (B,))
    expected = ref.add_noise(x0, eps, t)
    torch.testing.assert_close(schedule.add_noise(x0, eps, t[:, None].expand(B, T)), expected)


def test_per_slot_step_is_slotwise_diffusers_step():
    """Different levels per slot: every slot equals a diffusers step at that slot's own level."""
    src, ref = make("DDIM")
    schedule = PerSlotSchedule(src, 10)
    ref.set_timesteps(10)
    k = torch.randint(1, 11, (B, T))
    sample, out = torch.randn(B, T, A), torch.randn(B, T, A)
    got = schedule.step(out, k, sample)
    for b in range(B):
        for j in range(T):
            t = schedule.train_timesteps(k[b, j])
            ref_slot = ref.step(out[b : b + 1, j : j + 1], t, sample[b : b + 1, j : j + 1]).prev_sample
            torch.testing.assert_close(got[b, j], ref_slot[0, 0], rtol=1e-5, atol=1e-5)


def test_clean_slots_are_not_stepped():
    src, _ = make("DDPM")
    schedule = PerSlotSchedule(src, 100)
    k = torch.zeros(B, T, dtype=torch.long)
    k[:, T // 2 :] = 50
    sample = torch.randn(B, T, A)
    got = schedule.step(torch.randn(B, T, A), k, sample)
    assert torch.equal(got[:, : T // 2], sample[:, : T // 2])
    assert not torch.allclose(got[:, T // 2 :], sample[:, T // 2 :])
    assert torch.isfinite(got).all()


def test_steps_remaining_table_matches_set_timesteps():
    src, ref = make("DDPM")
    schedule = PerSlotSchedule(src, 10)
    ref.set_timesteps(10)
    assert schedule.train_timesteps(torch.tensor(0)) == -1
    assert schedule.train_timesteps(torch.arange(1, 11)).tolist() == ref.timesteps.flip(0).tolist()


def test_too_many_inference_steps_is_a_clear_error():
    src, _ = make("DDPM")
    with pytest.raises(ValueError, match="num_inference_steps"):
        PerSlotSchedule(src, 200)
