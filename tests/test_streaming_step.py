"""The streaming step without per-call waste (`buffer.stream_step`, `SDPModel.stream_step`, the step
embedding cache of `unet.py`) and compiled: cached == recomputed, compiled == eager, one graph."""

import pytest
import torch
from sdp_test_utils import history, observation, tiny_config

from lerobot_sdp import SDPPolicy
from lerobot_sdp.buffer import StreamNoise, step_noise
from lerobot_sdp.noise_schemes import NoiseSchemeWeights, sample_levels
from lerobot_sdp.observations import offline_history
from lerobot_sdp.schedule import gaussian_like
from lerobot_sdp.unet import PlanEmbeddingCache

STEP_CONDITIONINGS = ["flatten", "film_per_slot"]


def rollout(policy, n_actions: int, seed: int = 0, batch_size: int = 2) -> torch.Tensor:
    device = next(policy.parameters()).device
    g = torch.Generator(device).manual_seed(seed)
    obs = [observation(policy.config, batch_size, seed=100 + i) for i in range(n_actions)]
    dtype = next(policy.parameters()).dtype
    actions = [policy.select_action({k: v.to(device, dtype) for k, v in o.items()}, generator=g) for o in obs]
    return torch.stack(actions).float().cpu()


def count_encodings(policy) -> list[int]:
    """How often the step encoder really runs (its first layer), cache hits excluded."""
    calls = [0]
    encoder = policy.ema_model.unet.diffusion_step_encoder
    first = encoder.mlp[0] if hasattr(encoder, "mlp") else encoder[1]
    first.register_forward_hook(lambda *_: calls.__setitem__(0, calls[0] + 1))
    return calls


@pytest.mark.parametrize("step_conditioning", STEP_CONDITIONINGS)
def test_step_encoder_runs_once_per_plan_step_not_per_call(step_conditioning):
    policy = SDPPolicy(tiny_config(step_conditioning=step_conditioning)).eval()
    calls = count_encodings(policy)
    s = policy.geometry.steps_per_call
    rollout(policy, 5 * policy.config.n_action_steps)
    assert calls[0] == s  # s embeddings, then only cache hits
    policy.reset()
    rollout(policy, 3 * policy.config.n_action_steps, batch_size=3)  # a new plan: cached in its turn
    assert calls[0] == 2 * s


def uncached(monkeypatch):
    monkeypatch.setattr(PlanEmbeddingCache, "embed", lambda self, t, compute: compute(t))


@pytest.mark.parametrize("step_conditioning", STEP_CONDITIONINGS)
def test_cache_is_rebuilt_when_weights_dtype_or_batch_change(step_conditioning, monkeypatch):
    """The same stream with and without the cache, through the changes that must invalidate it: an
    in-place weight update (an optimiser step), bfloat16 autocast, a load_state_dict, a new batch
    size (a new plan) and, where CUDA exists, a move to the GPU. Any stale embedding changes the
    actions (or fails on a dtype or device mismatch)."""
    cfg = tiny_config(step_conditioning=step_conditioning)
    cached, other = SDPPolicy(cfg).eval(), SDPPolicy(cfg).eval()

    def run_stages(policy):
        out = [rollout(policy, 8, seed=1)]
        with torch.no_grad():
            for p in policy.ema_model.unet.diffusion_step_encoder.parameters():
                p.mul_(1.5)  # in place, as an optimiser step: same storage, new version
        out.append(rollout(policy, 8, seed=2))
        with torch.autocast("cpu", dtype=torch.bfloat16):  # LeRobot's step encoder works in float32 only
            out.append(rollout(policy, 8, seed=3))
        policy.load_state_dict(other.state_dict())
        out.append(rollout(policy, 8, seed=4))
        out.append(rollout(policy, 8, seed=5, batch_size=3))
        if torch.cuda.is_available():
            out.append(rollout(policy.cuda(), 8, seed=6))
        return out

    weights = {k: v.clone() for k, v in cached.state_dict().items()}
    stages = run_stages(cached)
    reference = SDPPolicy(cfg).eval()
    reference.load_state_dict(weights)
    uncached(monkeypatch)
    expected = run_stages(reference)
    names = ["initial", "in-place update", "bfloat16 autocast", "load_state_dict", "batch size 3", "cuda"]
    for name, got, want in zip(names, stages, expected, strict=False):
        torch.testing.assert_close(got, want, msg=lambda m, name=name: f"after {name}: {m}")


def test_streaming_steps_skip_the_inactive_slot_mask():
    policy = SDPPolicy(tiny_config()).eval()
    plan = policy._buffer.plan(torch.device("cpu"), 2)
    assert all(c.active is None for c in plan)  # every slot steps on every streaming step
    k = torch.tensor([[0, 1, 2, 3]])
    assert torch.equal(policy.model.schedule.coefficients(k).active.squeeze(-1), k > 0)


def test_non_finite_observation_leaves_the_buffer_as_it_was():
    """The NaN guard is read after the chunk is computed; a refused observation must not advance the
    stream nor stay in the observation history."""
    cfg = tiny_config()
    policy = SDPPolicy(cfg).eval()
    for i in range(cfg.n_action_steps):  # one chunk: the buffer is primed and shifted once
        policy.select_action(observation(cfg, 2, seed=i))
    before = policy._buffer.sample.clone()
    history = [list(q) for key, q in policy._queues.items() if key != "action"]
    bad = observation(cfg, 2, seed=50)
    bad["observation.state"][1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"`observation\.state` contains NaN or inf"):
        policy.select_action(bad)
    assert torch.equal(policy._buffer.sample, before)
    assert [list(q) for key, q in policy._queues.items() if key != "action"] == history  # same tensors
    assert policy.select_action(observation(cfg, 2, seed=51)).isfinite().all()


def test_training_levels_are_drawn_on_the_models_device():
    policy = SDPPolicy(tiny_config())
    schedule = policy.model.schedule.to("meta")  # no kernels run: only where tensors are made
    levels = sample_levels(NoiseSchemeWeights(0.25, 0.25, 0.25, 0.25), 8, policy.geometry, schedule)
    assert levels.device.type == "meta" and levels.shape == (8, policy.geometry.horizon)


def explain(policy, image: bool):
    cfg = policy.config
    model = policy._sampling_model()
    hist = offline_history(cfg, history(cfg, 1))
    policy._buffer.prime(torch.zeros(1, policy.geometry.horizon, 2))
    sample = policy._buffer.sample
    plan = policy._buffer.plan(sample.device, 1)
    noise = StreamNoise(step_noise(plan, sample, None), gaussian_like(sample))
    return torch._dynamo.explain(model.stream_step)(hist, sample, plan, noise)


@pytest.mark.parametrize("image", [False, True], ids=["state", "image"])
@pytest.mark.parametrize("scheduler", ["DDPM", "DDIM"])
@pytest.mark.parametrize("step_conditioning", STEP_CONDITIONINGS)
def test_streaming_step_is_one_graph_without_breaks(image, scheduler, step_conditioning):
    torch._dynamo.reset()
    cfg = tiny_config(image=image, noise_scheduler_type=scheduler, step_conditioning=step_conditioning)
    result = explain(SDPPolicy(cfg).eval(), image)
    assert result.graph_break_count == 0, [str(r.reason) for r in result.break_reasons]
    assert result.graph_count == 1


def test_compiled_streaming_equals_eager_and_keeps_checkpoint_keys():
    """`compile_model` and LeRobot's own `--use_torch_compile` wrapper (lerobot-rollout) give the eager
    actions to float tolerance, and compiling renames no weight."""
    from lerobot.rollout.context import _wrap_predict_action_chunk_with_torch_compile

    torch._dynamo.reset()
    eager = SDPPolicy(tiny_config()).eval()
    compiled = SDPPolicy(tiny_config(compile_model=True)).eval()
    assert compiled.state_dict().keys() == eager.state_dict().keys()
    compiled.load_state_dict(eager.state_dict())
    wrapped = SDPPolicy(tiny_config()).eval()
    wrapped.load_state_dict(eager.state_dict())
    assert _wrap_predict_action_chunk_with_torch_compile(wrapped, backend="inductor", mode="default")
    want = rollout(eager, 3 * eager.config.n_action_steps, batch_size=1)
    for policy in (compiled, wrapped):
        with torch.inference_mode():  # as lerobot-rollout's engines call it
            got = rollout(policy, 3 * policy.config.n_action_steps, batch_size=1)
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    assert compiled.ema_model._compiled_stream is not None and wrapped.ema_model._compiled_stream is not None
