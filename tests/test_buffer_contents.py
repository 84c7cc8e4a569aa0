"""The streaming buffer's *contents*, pinned against expectations computed independently of the code
under test (docs/algorithm.md, sections 2, 3 and 7).

`Reference` rebuilds every expected quantity from the paper's formulas and diffusers' own tables:
the chunk of every slot, the steps remaining k at the start of a call ((chunk + 1) * N/h), the
training timestep of k (diffusers' ``set_timesteps(N)``), abar of that timestep, and the posterior
of a DDPM step. The buffer is driven by oracle denoisers that know the true action sequence (a
smooth random walk), aligned with the buffer's position in it. With a perfect x0 (or epsilon) the
reverse process keeps every slot's marginal exact, so:

- after ``prime`` every slot is q(x_k | primer) at its start level;
- after ``stream_step`` the executed chunk equals the truth; the kept chunks moved by exactly one chunk
  (DDIM: every kept slot keeps its implied noise, exactly; DDPM: the kept slot follows the exact
  posterior q(x_k' | x_k, x0)); the past slots are the executed truth noised to chunk 0's level;
  the appended slots are fresh N(0, I).

Statistical checks are seeded and their tolerances come from the sample size (``Z`` standard errors).
"""

import math

import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler
from sdp_test_utils import stream_step_with

from lerobot_sdp.buffer import StreamingBuffer
from lerobot_sdp.geometry import ChunkGeometry
from lerobot_sdp.schedule import PerSlotSchedule

Z = 5.0  # standard errors allowed by every statistical check
N_TRAIN = 100
A = 2  # action dimensions

# (n_obs_steps To, chunk_len Tb, n_chunks h, N, U-Net downsampling, chunks streamed): past slots
# 0 / 1 / 2 / 3 (more than a chunk), padding 0 / 3, s = 1 / 3 / 4 / 5 / 6 / 25, h = 1 (plain DP)
# to 5, N below and equal to N_train.
GEOMETRIES = {
    "To2-Tb4-h2-N10-pad3": (2, 4, 2, 10, 4, 1000),
    "To3-Tb2-h4-N16-nopad": (3, 2, 4, 16, 2, 1000),
    "To1-Tb3-h3-N9-pad3": (1, 3, 3, 9, 4, 1000),
    "To2-Tb5-h1-N6-plainDP": (2, 5, 1, 6, 1, 1000),
    "To4-Tb2-h5-N5-s1": (4, 2, 5, 5, 8, 1000),
    "To2-Tb8-h4-N100-pad3": (2, 8, 4, 100, 4, 60),
}
SAMPLERS = [("DDIM", "sample"), ("DDPM", "sample"), ("DDIM", "epsilon"), ("DDPM", "epsilon")]


def diffusers_scheduler(kind: str, prediction_type: str = "sample", **kwargs):
    cls = DDIMScheduler if kind == "DDIM" else DDPMScheduler
    return cls(
        num_train_timesteps=N_TRAIN,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=False,
        prediction_type=prediction_type,
        **kwargs,
    )


class Reference:
    """Expected geometry and schedule values, from the paper's definitions and diffusers' tables only."""

    def __init__(self, kind: str, to: int, tb: int, h: int, n: int, down: int):
        self.n_past, self.chunk_len, self.n_chunks, self.n = to - 1, tb, h, n
        unpadded = self.n_past + h * tb
        self.horizon = math.ceil(unpadded / down) * down
        self.n_pad = self.horizon - unpadded
        self.s = n // h
        chunk = [0] * self.n_past + [j // tb for j in range(h * tb)] + [h - 1] * self.n_pad
        self.level = torch.tensor([(c + 1) * self.s for c in chunk])  # k at the start of a call
        self.executed = slice(self.n_past, self.n_past + tb)
        ref = diffusers_scheduler(kind)
        ref.set_timesteps(n)
        self.timesteps = ref.timesteps.long()  # descending: timesteps[n - k] is level k
        self.abar_train = ref.alphas_cumprod.double()
        # the level-0 ("clean") abar that diffusers' last step lands on
        self.abar_clean = float(getattr(ref, "final_alpha_cumprod", 1.0))

    def t_of(self, k: torch.Tensor) -> torch.Tensor:
        """Training timestep of steps-remaining k >= 1."""
        assert (k >= 1).all()
        return self.timesteps[self.n - k]

    def abar(self, k: torch.Tensor) -> torch.Tensor:
        """abar of steps-remaining k (0 = clean), shape (..., T, 1), float64."""
        out = torch.full(k.shape, self.abar_clean, dtype=torch.float64)
        out[k > 0] = self.abar_train[self.t_of(k[k > 0])]
        return out.unsqueeze(-1)


def build(kind: str, prediction_type: str, to: int, tb: int, h: int, n: int, down: int):
    geometry = ChunkGeometry(
        n_obs_steps=to, chunk_len=tb, n_chunks=h, num_inference_steps=n, downsampling=down
    )
    schedule = PerSlotSchedule(diffusers_scheduler(kind, prediction_type), n)
    return StreamingBuffer(geometry, schedule), Reference(kind, to, tb, h, n, down)


def true_actions(batch: int, length: int, seed: int) -> torch.Tensor:
    """A smooth random walk per (sample, dimension), around +1 so that a mean shift is visible."""
    g = torch.Generator().manual_seed(seed)
    walk = torch.cumsum(0.15 * torch.randn(batch, length, A, generator=g, dtype=torch.float64), dim=1)
    return (1.0 + 0.5 * torch.tanh(walk)).float()


class Oracle:
    """Denoiser that knows the true sequence: returns it ("sample") or the exact noise of the input
    ("epsilon", from diffusers' abar of the timesteps it is given), and records what it was given."""

    def __init__(self, truth: torch.Tensor, ref: Reference, prediction_type: str):
        self.truth, self.ref, self.prediction_type = truth, ref, prediction_type
        self.chunk = 0  # the buffer's position in the truth, in chunks
        self.timesteps: list[torch.Tensor] = []

    def x0(self, chunk: int | None = None) -> torch.Tensor:
        start = (self.chunk if chunk is None else chunk) * self.ref.chunk_len
        return self.truth[:, start : start + self.ref.horizon]

    def __call__(self, sample: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        assert sample.shape == (self.truth.shape[0], self.ref.horizon, A)
        self.timesteps.append(timesteps.clone())
        x0 = self.x0()
        if self.prediction_type == "sample":
            return x0.clone()
        abar = self.ref.abar_train[timesteps].unsqueeze(-1)
        return ((sample.double() - abar.sqrt() * x0) / (1 - abar).sqrt()).float()


def assert_standard_normal(z: torch.Tensor, what: str) -> None:
    """Mean 0 and variance 1, within Z standard errors of their estimates."""
    z = z.double().flatten()
    n = z.numel()
    mean, var = z.mean().item(), z.var().item()
    assert abs(mean) < Z / math.sqrt(n), f"{what}: mean {mean:.4f} over {n} samples, expected 0"
    assert abs(var - 1) < Z * math.sqrt(2 / (n - 1)), f"{what}: variance {var:.4f} over {n}, expected 1"


def assert_gaussian(x: torch.Tensor, mean: torch.Tensor, var: torch.Tensor, what: str) -> None:
    """Empirical mean and variance over the batch, per slot and dimension, against N(mean, var)."""
    n = x.shape[0]
    x = x.double()
    emp_mean, emp_var = x.mean(0), x.var(0)
    mean, var = mean.expand_as(emp_mean), var.expand_as(emp_var)
    bad_mean = (emp_mean - mean).abs() > Z * (var / n).sqrt()
    bad_var = (emp_var - var).abs() > Z * var * math.sqrt(2 / (n - 1))
    assert not bad_mean.any(), f"{what}: slot means off at (slot, dim) {bad_mean.nonzero().tolist()}"
    assert not bad_var.any(), f"{what}: slot variances off at (slot, dim) {bad_var.nonzero().tolist()}"


# --- prime -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["DDIM", "DDPM"])
@pytest.mark.parametrize("name", list(GEOMETRIES))
def test_prime_is_the_forward_process_at_each_slots_start_level(name, kind):
    """After prime, slot j ~ q(x_k | primer) = N(sqrt(abar_k) primer, (1 - abar_k) I), k = its start level."""
    to, tb, h, n, down, _ = GEOMETRIES[name]
    buffer, ref = build(kind, "sample", to, tb, h, n, down)
    torch.manual_seed(0)
    batch = 20_000
    # one clean sequence shared by the batch, different in every slot, away from 0
    primer = (0.5 + torch.rand(1, ref.horizon, A)).expand(batch, -1, -1).contiguous()
    buffer.prime(primer, torch.Generator().manual_seed(1))
    assert buffer.sample.shape == (batch, ref.horizon, A)
    abar = ref.abar(ref.level)
    assert_gaussian(buffer.sample, abar.sqrt() * primer[0].double(), 1 - abar, f"{name} {kind} prime")


# --- stream_step ------------------------------------------------------------------------------------


def check_advance(ref, oracle, kind, before, chunk, after, residuals):
    """One ``stream_step`` against the reference: exact where the process is deterministic, else the
    standardised residuals of each slot group are collected for ``assert_standard_normal``."""
    n_past, tb, level = ref.n_past, ref.chunk_len, ref.level
    x0_old, x0_new = oracle.x0(oracle.chunk), oracle.x0(oracle.chunk + 1)  # truth aligned before / after
    torch.testing.assert_close(chunk, x0_old[:, ref.executed], atol=2e-4, rtol=0)

    # kept chunks: new slot j (n_past <= j < n_past + (h-1) Tb) is old slot j + Tb after s steps
    kept = slice(n_past, n_past + (ref.n_chunks - 1) * tb)
    old = slice(n_past + tb, n_past + ref.n_chunks * tb)
    if kept.stop > kept.start:
        a_from, a_to = ref.abar(level[old]), ref.abar(level[kept])  # k and k - s
        x_t, x0 = before[:, old].double(), x0_old[:, old].double()
        if kind == "DDIM":  # deterministic: every slot keeps the noise it was drawn with
            eps = (x_t - a_from.sqrt() * x0) / (1 - a_from).sqrt()
            expected = a_to.sqrt() * x0 + (1 - a_to).sqrt() * eps
            torch.testing.assert_close(after[:, kept].double(), expected, atol=2e-4, rtol=1e-4)
        else:  # DDPM: the exact posterior q(x_{k-s} | x_k, x0) of the s steps
            ratio = a_from / a_to
            mean = (
                a_to.sqrt() * (1 - ratio) / (1 - a_from) * x0 + ratio.sqrt() * (1 - a_to) / (1 - a_from) * x_t
            )
            var = (1 - a_to) * (1 - ratio) / (1 - a_from)
            residuals["kept"].append((after[:, kept].double() - mean) / var.sqrt())

    # past slots: the executed truth noised to chunk 0's start level
    if n_past:
        a = ref.abar(level[:n_past])
        x0 = x0_new[:, :n_past].double()
        residuals["past"].append((after[:, :n_past].double() - a.sqrt() * x0) / (1 - a).sqrt())

    # appended last chunk and padding: fresh N(0, I)
    residuals["tail"].append(after[:, n_past + (ref.n_chunks - 1) * tb :])


@pytest.mark.parametrize("kind, prediction_type", SAMPLERS)
@pytest.mark.parametrize("name", list(GEOMETRIES))
def test_oracle_stream_contents_over_many_chunks(name, kind, prediction_type):
    """1,000 consecutive chunks (60 at N = 100): with an oracle denoiser the executed chunk equals the
    true actions every time, the denoiser sees the paper's staircase s times per chunk, and the buffer
    after every shift holds exactly what section 7 prescribes."""
    to, tb, h, n, down, n_stream = GEOMETRIES[name]
    buffer, ref = build(kind, prediction_type, to, tb, h, n, down)
    batch = 4
    truth = true_actions(batch, (n_stream + 1) * tb + ref.horizon, seed=7)
    oracle = Oracle(truth, ref, prediction_type)
    g = torch.Generator().manual_seed(3)
    buffer.prime(oracle.x0(), g)
    expected_t = [ref.t_of(ref.level - j).expand(batch, -1) for j in range(ref.s)]
    residuals = {"kept": [], "past": [], "tail": []}
    for c in range(n_stream):
        before = buffer.sample.clone()
        oracle.timesteps.clear()
        chunk = stream_step_with(buffer, oracle, g)
        assert len(oracle.timesteps) == ref.s, f"chunk {c}: {len(oracle.timesteps)} denoiser calls"
        for j, (got, want) in enumerate(zip(oracle.timesteps, expected_t, strict=True)):
            assert torch.equal(got, want), f"chunk {c}, call {j}: timesteps {got[0].tolist()}"
        assert buffer.sample.shape == before.shape
        check_advance(ref, oracle, kind, before, chunk, buffer.sample, residuals)
        oracle.chunk += 1
    for group, values in residuals.items():
        if values:
            assert_standard_normal(torch.cat(values, dim=1), f"{name} {kind} {group} slots")


@pytest.mark.parametrize("kind", ["DDIM", "DDPM"])
def test_advance_contents_per_slot_with_a_large_batch(kind):
    """The same contents slot by slot (not pooled), over a large batch and three shifts: every past
    slot at chunk 0's level, every appended slot N(0, I), every kept slot q(x_k | truth) at its new
    start level. N = N_train, so that level N is pure noise (abar = 2e-7) and a slot appended as
    N(0, I) is q(x_N | truth) too: the whole buffer stays on the forward process."""
    to, tb, h, n, down = 3, 2, 4, 100, 4  # 2 past slots, 2 padding slots, s = 25
    buffer, ref = build(kind, "sample", to, tb, h, n, down)
    batch = 20_000
    truth = true_actions(1, 4 * tb + ref.horizon, seed=11).expand(batch, -1, -1)
    oracle = Oracle(truth, ref, "sample")
    g = torch.Generator().manual_seed(5)
    buffer.prime(oracle.x0(), g)
    abar = ref.abar(ref.level)
    for _ in range(3):
        chunk = stream_step_with(buffer, oracle, g)
        torch.testing.assert_close(chunk, oracle.x0()[:, ref.executed], atol=2e-4, rtol=0)
        oracle.chunk += 1
        x0 = oracle.x0()[0].double()
        fresh = slice(ref.n_past + (h - 1) * tb, ref.horizon)
        mean = abar.sqrt() * x0
        mean[fresh] = 0.0
        var = (1 - abar).expand(-1, A).clone()
        var[fresh] = 1.0
        assert_gaussian(buffer.sample, mean, var, f"{kind} after shift {oracle.chunk}")


def test_past_re_noise_and_appended_tail_are_independent_draws():
    """The re-noised past slots and the appended N(0, I) slots get their own noise: over a large batch
    the standardised past residuals are uncorrelated with every appended slot."""
    to, tb, h, n, down = 3, 2, 4, 100, 4  # 2 past slots
    buffer, ref = build("DDIM", "sample", to, tb, h, n, down)
    batch = 20_000
    truth = true_actions(1, 2 * tb + ref.horizon, seed=13).expand(batch, -1, -1)
    oracle = Oracle(truth, ref, "sample")
    buffer.prime(oracle.x0(), torch.Generator().manual_seed(9))
    stream_step_with(buffer, oracle, torch.Generator().manual_seed(10))
    oracle.chunk += 1
    a = ref.abar(ref.level[: ref.n_past])
    past = (buffer.sample[:, : ref.n_past].double() - a.sqrt() * oracle.x0()[:, : ref.n_past]) / (
        1 - a
    ).sqrt()
    tail = buffer.sample[:, ref.n_past + (h - 1) * tb :].double()
    for i in range(past.shape[1]):
        for j in range(tail.shape[1]):
            for d in range(A):
                r = torch.corrcoef(torch.stack([past[:, i, d], tail[:, j, d]]))[0, 1].item()
                assert abs(r) < Z / math.sqrt(batch), f"past slot {i} and tail slot {j}, dim {d}: r = {r:.3f}"


# --- randomness -----------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["DDIM", "DDPM"])
def test_one_generator_reproduces_the_stream_and_leaves_the_global_rng_alone(kind):
    """Every draw (primer noise, DDPM step noise, re-noised past, appended tail) comes from the
    generator: the same seed gives the same buffers whatever the global RNG state, and the global RNG
    is not consumed; another seed changes the stream."""
    to, tb, h, n, down, _ = GEOMETRIES["To3-Tb2-h4-N16-nopad"]

    def stream(seed: int, global_seed: int) -> list[torch.Tensor]:
        buffer, ref = build(kind, "epsilon", to, tb, h, n, down)
        torch.manual_seed(global_seed)
        state = torch.get_rng_state()
        g = torch.Generator().manual_seed(seed)
        buffer.prime(torch.zeros(2, ref.horizon, A), g)
        out = [buffer.sample.clone()]
        for _ in range(3):
            out.append(stream_step_with(buffer, lambda x, t: 0.1 * x, g))
            out.append(buffer.sample.clone())
        assert torch.equal(torch.get_rng_state(), state), "the global RNG was used"
        return out

    first, again, other = stream(1, 0), stream(1, 123), stream(2, 0)
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(first[-1], other[-1])


def test_clean_end_follows_diffusers_final_alpha_cumprod():
    """DDIM built with set_alpha_to_one=False ends on abar_0, not 1 (diffusers' final_alpha_cumprod):
    the last streaming step must equal diffusers' step there too."""
    src = diffusers_scheduler("DDIM", "epsilon", set_alpha_to_one=False)
    ref = diffusers_scheduler("DDIM", "epsilon", set_alpha_to_one=False)
    schedule = PerSlotSchedule(src, 10)
    ref.set_timesteps(10)
    torch.manual_seed(0)
    sample, out = torch.randn(2, 6, A), torch.randn(2, 6, A)
    got = schedule.step(out, torch.ones(2, 6, dtype=torch.long), sample)
    expected = ref.step(out, ref.timesteps[-1], sample).prev_sample
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
