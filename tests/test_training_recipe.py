"""The training-recipe options: chunk-wise levels over the whole training table, the noise-scheme
curriculum (and its step across a checkpoint), Min-SNR-gamma loss weights, a larger constant share."""

import math
from collections import Counter

import draccus
import pytest
import torch
from diffusers import DDPMScheduler
from sdp_test_utils import history, tiny_config

from lerobot_sdp import SDPConfig, SDPPolicy
from lerobot_sdp.geometry import ChunkGeometry
from lerobot_sdp.loss_weighting import min_snr_weights
from lerobot_sdp.noise_schemes import NoiseCurriculum, NoiseSchemeWeights, sample_levels
from lerobot_sdp.schedule import PerSlotSchedule

CHUNKWISE = NoiseSchemeWeights(constant=0.0, chunkwise=1.0)


def table_setup(num_train_timesteps, n_chunks, n_inference):
    g = ChunkGeometry(
        n_obs_steps=2, chunk_len=4, n_chunks=n_chunks, num_inference_steps=n_inference, downsampling=4
    )
    scheduler = DDPMScheduler(num_train_timesteps=num_train_timesteps, beta_schedule="squaredcos_cap_v2")
    return g, PerSlotSchedule(scheduler, n_inference)


def chunk_levels(levels, g):
    """Each row's level per chunk, checking that every slot of a chunk shares it."""
    per_chunk = []
    for chunk in range(g.n_chunks):
        slots = levels[:, g.slot_chunk == chunk]
        assert (slots == slots[:, :1]).all()
        per_chunk.append(slots[:, 0])
    return [tuple(row) for row in torch.stack(per_chunk, 1).tolist()]


@pytest.mark.parametrize(
    "num_train_timesteps, n_chunks, n_inference, pairs",
    [
        # by hand: T = 10, h = 2 -> bands of 5 timesteps, one offset shared by both chunks
        (10, 2, 10, {(0, 5), (1, 6), (2, 7), (3, 8), (4, 9)}),
        # by hand: T = 12, h = 4, the sampler at N = 4 (its grid has 1 staircase: the full table has 3)
        (12, 4, 4, {(0, 3, 6, 9), (1, 4, 7, 10), (2, 5, 8, 11)}),
        # the authors' get_diff_steps_training at T = 100, h = 2: floor(N (i+1) / h) - 1 - j, j in 0..49
        (100, 2, 16, {(49 - j, 99 - j) for j in range(50)}),
    ],
)
def test_training_table_draw_visits_exactly_the_authors_level_tuples_uniformly(
    num_train_timesteps, n_chunks, n_inference, pairs
):
    g, sched = table_setup(num_train_timesteps, n_chunks, n_inference)
    n = 1000 * len(pairs)
    torch.manual_seed(0)
    levels = sample_levels(CHUNKWISE, n, g, sched, chunkwise_grid="training_table")
    counts = Counter(chunk_levels(levels, g))
    assert set(counts) == pairs
    # each tuple with probability 1 / len(pairs): 1000 expected, binomial s.e. < 32, 5 of them
    assert all(abs(c - 1000) < 160 for c in counts.values())


def test_the_sampler_grid_draw_is_unchanged_and_reaches_fewer_pairs():
    g, sched = table_setup(100, 2, 16)
    torch.manual_seed(0)
    default = sample_levels(CHUNKWISE, 4000, g, sched)
    torch.manual_seed(0)
    explicit = sample_levels(CHUNKWISE, 4000, g, sched, chunkwise_grid="sampler")
    assert torch.equal(default, explicit)
    # DDIM/DDPM 16 over 100 timesteps: steps of 6 (diffusers' leading spacing), k = 1..8 and 9..16
    assert set(chunk_levels(default, g)) == {(6 * (k - 1), 6 * (k + 7)) for k in range(1, 9)}


def test_curriculum_share_switches_or_ramps_at_the_configured_steps():
    switch = NoiseCurriculum(constant_steps=3)
    assert [float(switch.constant_share(torch.tensor(s))) for s in range(5)] == [1, 1, 1, 0, 0]
    ramp = NoiseCurriculum(constant_steps=2, ramp_steps=4)
    shares = [float(ramp.constant_share(torch.tensor(s))) for s in range(8)]
    assert shares == [1, 1, 1, 0.75, 0.5, 0.25, 0, 0]
    assert not NoiseCurriculum().enabled and switch.enabled and NoiseCurriculum(ramp_steps=1).enabled
    with pytest.raises(ValueError, match="noise_curriculum steps must be >= 0"):
        NoiseCurriculum(constant_steps=-1)


def training_batch(cfg, batch_size=16):
    batch = history(cfg, batch_size)
    batch["action"] = torch.rand(batch_size, cfg.horizon, 2) * 2 - 1
    return batch


def constant_rows(policy, cfg, seen):
    """One training step as lerobot-train takes it (the loss, then `update()` after the optimiser),
    recording the U-Net's timesteps: the share of the batch's rows drawn at one level."""
    seen.clear()
    policy.forward(training_batch(cfg))
    policy.update()
    t = seen[-1]
    return float((t == t[:, :1]).all(dim=1).float().mean())


def recording(policy):
    seen = []
    unet = policy.model.unet
    forward = unet.forward

    def record(x, t, global_cond=None):
        seen.append(t.detach().clone())
        return forward(x, t, global_cond=global_cond)

    unet.forward = record
    return seen


@pytest.mark.parametrize("use_ema", [False, True])
def test_curriculum_switches_at_its_step_and_resumes_from_a_checkpoint(tmp_path, use_ema):
    cfg = tiny_config(
        noise_schemes={"constant": 0.0, "chunkwise": 1.0},
        noise_curriculum={"constant_steps": 3},
        use_ema=use_ema,
    )
    torch.manual_seed(0)
    policy = SDPPolicy(cfg).train()
    seen = recording(policy)
    # steps 0 and 1 before the checkpoint: every row at one level (chunk-wise never is)
    assert [constant_rows(policy, cfg, seen) for _ in range(2)] == [1.0, 1.0]
    policy.save_pretrained(tmp_path)
    resumed = SDPPolicy.from_pretrained(tmp_path).train()  # what `lerobot-train --resume=true` builds
    assert resumed.config.noise_curriculum == NoiseCurriculum(constant_steps=3)
    assert int(resumed.ema_step) == 2
    seen = recording(resumed)
    assert constant_rows(resumed, cfg, seen) == 1.0  # step 2: still constant
    assert [constant_rows(resumed, cfg, seen) for _ in range(2)] == [0.0, 0.0]  # steps 3, 4: the mixture
    fresh = SDPPolicy(cfg).train()  # a run started over would be back at step 0
    assert constant_rows(fresh, cfg, recording(fresh)) == 1.0


def test_the_default_recipe_weighs_slots_by_min_snr_5():
    cfg = tiny_config()
    assert cfg.min_snr_gamma == 5.0 and cfg.chunkwise_grid == "sampler" and not cfg.noise_curriculum.enabled


def test_the_papers_unweighted_loss_draws_nothing_more(tmp_path):
    """`min_snr_gamma=None` and no curriculum train as the paper's Eq. 5, draw for draw: the same loss
    from the same seed."""
    cfg = tiny_config(min_snr_gamma=None)
    policy = SDPPolicy(cfg).train()
    batch = training_batch(cfg)
    torch.manual_seed(1)
    loss = policy.model.compute_loss(batch)  # no step: only the curriculum needs one
    state = torch.get_rng_state()
    torch.manual_seed(1)
    global_cond = policy.model.global_conditioning(batch)
    levels = sample_levels(cfg.noise_schemes, 16, policy.model.geometry, policy.model.schedule)
    eps = torch.randn(batch["action"].shape)
    x_t = policy.model.schedule.add_noise(batch["action"], eps, levels)
    expected = torch.nn.functional.mse_loss(policy.model.unet(x_t, levels, global_cond=global_cond), eps)
    torch.testing.assert_close(loss, expected, atol=0, rtol=0)
    assert torch.equal(torch.get_rng_state(), state)
    curriculum = SDPPolicy(tiny_config(noise_curriculum={"constant_steps": 1}))
    with pytest.raises(ValueError, match="noise_curriculum needs the training step"):
        curriculum.model.compute_loss(batch)


def squaredcos_abar(t, n=100):
    """abar_t of diffusers' squaredcos_cap_v2 written out: the betas 1 - f((i+1)/n) / f(i/n) with
    f(x) = cos((x + 0.008) / 1.008 * pi / 2)^2 telescope to f((t+1)/n) / f(0) (the 0.999 cap only
    bites at t = n-1)."""

    def f(x):
        return math.cos((x + 0.008) / 1.008 * math.pi / 2) ** 2

    return f((t + 1) / n) / f(0)


def linear_abar(t, n=100):
    """abar_t of the linear schedule: betas evenly from 1e-4 to 0.02, multiplied out."""
    return math.prod(1 - (1e-4 + i * (0.02 - 1e-4) / (n - 1)) for i in range(t + 1))


@pytest.mark.parametrize(
    "beta_schedule, abar", [("squaredcos_cap_v2", squaredcos_abar), ("linear", linear_abar)]
)
@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_min_snr_weights_match_the_hand_worked_values(beta_schedule, abar, prediction_type):
    scheduler = DDPMScheduler(num_train_timesteps=100, beta_schedule=beta_schedule)
    sched = PerSlotSchedule(scheduler, 10)
    ts = [0, 5, 20, 40, 60, 90]
    weights = min_snr_weights(sched, torch.tensor([ts]), 5.0, prediction_type).flatten().tolist()
    for t, w in zip(ts, weights, strict=True):
        snr = abar(t) / (1 - abar(t))
        expected = min(snr, 5.0) / snr if prediction_type == "epsilon" else min(snr, 5.0)
        assert w == pytest.approx(expected, rel=2e-4), t
    if beta_schedule == "linear":  # t = 0 by hand: abar 0.9999, SNR 9999 (float32: 1 - abar to 2e-4)
        assert weights[0] == pytest.approx(5 / 9999 if prediction_type == "epsilon" else 5.0, rel=5e-4)
    # the noisiest levels (SNR < 5) keep their full weight under epsilon prediction
    assert (weights[-1] == pytest.approx(1.0)) == (prediction_type == "epsilon")


def test_a_clean_slot_weighs_nothing_under_epsilon_prediction():
    sched = PerSlotSchedule(DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2"), 10)
    w = min_snr_weights(sched, torch.tensor([[-1, 50]]), 5.0, "epsilon").flatten()
    assert w[0] == 0 and torch.isfinite(w).all()


def test_the_loss_weighs_every_slot_by_its_min_snr_weight():
    cfg = tiny_config(min_snr_gamma=5.0, noise_schemes={"constant": 0.5, "chunkwise": 0.5})
    policy = SDPPolicy(cfg).train()
    seen = []

    def zero_net(x, t, global_cond=None):
        seen.append((x.detach().clone(), t.clone()))
        return torch.zeros_like(x)

    policy.model.unet.forward = zero_net
    batch = training_batch(cfg, 64)
    batch["action"] = torch.zeros_like(batch["action"])  # x_t = sqrt(1 - abar) eps: eps is readable
    loss = policy.model.compute_loss(batch)
    x, t = seen[0]
    abar = torch.tensor([[squaredcos_abar(v) for v in row] for row in t.tolist()], dtype=torch.float64)
    eps2 = x.double().pow(2) / (1 - abar).unsqueeze(-1)  # the loss of a zero prediction: eps^2
    snr = abar / (1 - abar)
    weight = (snr.clamp(max=5.0) / snr).unsqueeze(-1)
    torch.testing.assert_close(loss.double(), (weight * eps2).mean(), rtol=1e-4, atol=0)


def test_the_new_options_parse_from_the_command_line_and_refuse_bad_values():
    cfg = draccus.parse(
        SDPConfig,
        args=[
            "--noise_schemes.constant=0.5",
            "--noise_schemes.chunkwise=0.5",
            "--chunkwise_grid=training_table",
            "--noise_curriculum.constant_steps=2000",
            "--noise_curriculum.ramp_steps=1000",
            "--min_snr_gamma=5",
        ],
    )
    assert cfg.noise_schemes.as_dict() == {
        "constant": 0.5,
        "linear": 0.0,
        "independent": 0.0,
        "chunkwise": 0.5,
        "independent_chunks": 0.0,
    }
    assert cfg.chunkwise_grid == "training_table" and cfg.min_snr_gamma == 5.0
    assert draccus.parse(SDPConfig, args=["--min_snr_gamma=null"]).min_snr_gamma is None  # the paper's loss
    assert cfg.noise_curriculum == NoiseCurriculum(constant_steps=2000, ramp_steps=1000)
    with pytest.raises(ValueError, match="noise_schemes weights must be >= 0"):
        NoiseSchemeWeights(constant=-0.5, chunkwise=0.5)
    with pytest.raises(ValueError, match="`chunkwise_grid` must be one of"):
        SDPConfig(chunkwise_grid="table")
    with pytest.raises(ValueError, match="make `num_train_timesteps` a multiple of `n_chunks`"):
        SDPConfig(
            chunkwise_grid="training_table", n_chunks=4, num_train_timesteps=102, num_inference_steps=16
        )
    with pytest.raises(ValueError, match="`min_snr_gamma` must be positive"):
        SDPConfig(min_snr_gamma=0.0)
