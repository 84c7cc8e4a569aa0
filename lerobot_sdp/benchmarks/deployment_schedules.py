"""Random deployment schedules on a virtual clock: every executed action checked, per engine.

    lerobot-sdp-bench schedules --schedules 1000 --seed 0 --output_dir outputs/benchmarks/schedules

SDP's policy server driven as LeRobot's `RobotClient` drives it, and SDP's RTC adapter driven as
LeRobot's RTC engine drives it (its `ActionQueue`), with random inference times, loop jitter,
restarts with and without Ready, reconnects, transient failures, slow first calls and clients that
vanish. Output: OUTPUT_DIR/results.json (per engine setting: actions executed, streams, the seeds
whose schedule broke a checked property, with the property).

What runs is the deployment code itself: `policy_server.SDPPolicyServer` and its sessions (LeRobot's
`PolicyServer` underneath: its observation filters, queue and timing), `SDPPolicy._rtc_chunk` and
LeRobot's `ActionQueue`. Only the denoiser is replaced, by a *coded stream*: action i of chunk k of
stream s is (s, k * Tb + i), so an executed action says which stream it came from and where in it.
The clock is virtual: a schedule of thousands of ticks runs in milliseconds, the same every time.

Checked after every event (`InvariantError` names the first broken one):
- every action the robot executes belongs to a stream started in its current episode, and runs once,
  in stream order, none skipped (`ActionLog`);
- async: a streamed chunk starts at most `delay_ticks` + 1 ticks after its observation, and the robot
  waits (after its episode's first action) at most the calls in flight take, plus one tick;
- RTC: each chunk starts max(K, ticks its call took) + 1 ticks after its frame;
- async: a vanished client's session is gone `session_timeout_s` and a quarter after its last call.

LeRobot's RTC engine (0.6.1) drops ceil(latency / tick) actions of a result, whatever ran: a call that
ends in the last part of a tick repeats one action, and an episode's slow first call loses the actions
it did not run. `run_rtc(..., queue_class=...)` takes the engine's `ActionQueue` with
docs/upstream/lerobot-0.6.1-rtc-actions-run.patch applied, which drops the actions that ran; with
LeRobot's own class those two deviations are counted (`repeated`, `lost_at_start`), not failures.
"""

import argparse
import contextlib
import heapq
import importlib.util
import logging
import math
import random
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import torch
from lerobot.async_inference.helpers import TimedObservation
from lerobot.policies.rtc import ActionQueue
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

TB = 8  # actions per chunk
FPS = 10
DT = 1 / FPS
POLL_S = 0.01  # LeRobot's RTC thread sleeps this long between looks at the queue
RETRY_S = 0.5  # and this long after a failed call
EVENTS = {"async": ("ready", "restart", "reconnect", "vanish"), "rtc": ("reset",)}


@dataclass(frozen=True)
class Step:
    """What happens on one control tick of a schedule."""

    jitter: float = 0.0  # the control loop runs this fraction of a tick late
    latency: float = 0.02  # seconds a call started during this tick takes
    fail: bool = False  # a call started during this tick fails (a transient error)
    event: str = ""  # before the tick: see EVENTS


class InvariantError(AssertionError):
    """A checked property broken by a schedule."""


def random_schedule(rng: random.Random, engine: str, ticks: int) -> list[Step]:
    """Ticks with random loop jitter (up to 0.4 tick) and call times (mostly 5-120 ms, one in seven up
    to 0.5 s; the first call of each episode 0.2-1.5 s slower: priming, warm-up), 3 % failures and 2 %
    events."""
    steps, first_call = [], True
    for _ in range(ticks):
        event = rng.choice(EVENTS[engine]) if rng.random() < 0.02 else ""
        latency = rng.uniform(0.005, 0.5 if rng.random() < 0.15 else 0.12)
        if first_call or event in ("ready", "restart", "reset", "vanish"):
            latency += rng.uniform(0.2, 1.5)
        first_call = False
        steps.append(Step(round(rng.uniform(0, 0.4), 3), round(latency, 4), rng.random() < 0.03, event))
    return steps


def shrink(steps: list[Step], fails) -> list[Step]:
    """A smaller schedule that still `fails` (a predicate): the shortest failing prefix, then each tick
    dropped, or made plain (a 20 ms call, no event, failure or jitter) in part or whole, while it fails."""
    low, high = 1, len(steps)  # a prefix of `high` ticks fails; find the shortest (bisection)
    while low < high:
        mid = (low + high) // 2
        low, high = (low, mid) if fails(steps[:mid]) else (mid + 1, high)
    steps = steps[:high]
    i = 0
    while i < len(steps):
        candidates = [None, Step(), replace(steps[i], event=""), replace(steps[i], fail=False)]
        candidates += [replace(steps[i], jitter=0.0), replace(steps[i], latency=Step.latency)]
        for candidate in candidates:
            tried = [*steps[:i], *([candidate] if candidate else []), *steps[i + 1 :]]
            if candidate != steps[i] and fails(tried):
                steps = tried
                break
        else:
            i += 1
    return steps


class Clock:
    now = 0.0

    def __call__(self) -> float:
        return self.now


@dataclass
class ActionLog:
    """The robot's executed actions, checked as they run: (stream, position) codes, from streams
    started in the current episode, in the stream's order, once each, none skipped. `lenient` (LeRobot's
    own RTC delay model) counts a repeat of the last action and skips forward instead of failing."""

    lenient: bool = False
    episode_start: float = -1.0
    stream_started: dict[int, float] = field(default_factory=dict)
    last: tuple[int, int] | None = None
    executed: int = 0
    repeated: int = 0
    skipped: int = 0

    def new_episode(self, now: float) -> None:
        self.episode_start, self.last = now, None

    def run(self, code: torch.Tensor, tick: int) -> None:
        stream, pos = (round(float(v)) for v in code)
        if self.stream_started.get(stream, -1.0) < self.episode_start:
            raise InvariantError(
                f"tick {tick}: action {pos} of stream {stream}, which is not of this episode"
            )
        expected = 0 if self.last is None or self.last[0] != stream else self.last[1] + 1
        if self.lenient and pos == expected - 1 and expected > 0:
            self.repeated += 1
        elif self.lenient and pos > expected:
            self.skipped += pos - expected
        elif pos != expected:
            raise InvariantError(f"tick {tick}: stream {stream} ran its action {pos}, expected {expected}")
        self.last, self.executed = (stream, pos), self.executed + 1


class CodedStream:
    """The denoiser's stand-in: chunk k of stream s is (s, k * Tb + i); a new stream after a reset.
    `latency` seconds pass on `clock` per call; `fail` makes the next call raise, leaving it as it was."""

    def __init__(self, log: ActionLog, clock: Clock, max_delay: int = 0):
        self.log, self.clock = log, clock
        self.stream, self.pos, self.latency, self.fail = None, 0, 0.0, False
        self.committed: list[int] = []
        self.config = SimpleNamespace(
            n_action_steps=TB,
            n_obs_steps=2,
            max_delay=max_delay,
            image_features={},
            input_features={OBS_STATE: None, OBS_ENV_STATE: None},
        )

    def reset(self) -> None:
        self.stream = None

    drop_queued_actions = reset

    def chunk(self, committed: int = 0) -> torch.Tensor:
        start = self.clock.now
        self.clock.now += self.latency
        if self.fail:
            raise RuntimeError("a transient failure (CUDA out of memory)")
        if self.stream is None:
            self.stream, self.pos = len(self.log.stream_started), 0
            self.log.stream_started[self.stream] = start
        codes = [[float(self.stream), float(self.pos + i)] for i in range(TB)]
        self.pos += TB
        self.committed.append(committed)
        return torch.tensor([codes])

    def predict_action_chunk(self, history, committed: int = 0) -> torch.Tensor:
        return self.chunk(committed)


# ----------------------------------------------------------------------------------------------------
# Async inference: SDPPolicyServer, driven as LeRobot's RobotClient drives it
# ----------------------------------------------------------------------------------------------------


def split_state(observation: dict) -> dict:
    """The policy's preprocessor as far as the server needs it: pusht_sim's 18 values, split."""
    state = observation[OBS_STATE].float()
    return {OBS_STATE: state[..., :2], OBS_ENV_STATE: state[..., 2:]}


class Peer:
    """A gRPC context: the client's id in metadata, as the hardened client sends it."""

    def __init__(self, client_id: str):
        self.client_id = client_id

    def peer(self) -> str:
        return "ipv4:127.0.0.1:1"

    def invocation_metadata(self):
        return (("x-sdp-client-id", self.client_id),)


class AsyncRun:
    """One schedule: a RobotClient (its queue, `must_go`, `chunk_size_threshold` 0.5 and
    `weighted_average` merge, one GetActions at a time) against `SDPPolicyServer`, at 10 Hz."""

    def __init__(self, steps: list[Step], max_delay: int, session_timeout_s: float = 2.0):
        from lerobot.utils.feature_utils import hw_to_dataset_features

        from lerobot_sdp import policy_server
        from lerobot_sdp.robots.pusht_sim import AGENT_KEYS, KEYPOINT_KEYS

        self.server_mod, self.steps, self.clock, self.log = policy_server, steps, Clock(), ActionLog()
        config = policy_server.SDPPolicyServerConfig(
            fps=FPS,
            inference_latency=0.0,
            session_timeout_s=session_timeout_s,
            obs_queue_timeout=0.0,
            max_clients=16,  # clients that vanished keep theirs until the sweep
        )
        self.service = policy_server.SDPPolicyServer(config, self.clock)
        self.features = hw_to_dataset_features(
            dict.fromkeys(AGENT_KEYS + KEYPOINT_KEYS, float), "observation"
        )
        self.keys, self.max_delay = AGENT_KEYS + KEYPOINT_KEYS, max_delay
        self.events: list = []  # (time, order, kind, data)
        self.order, self.client, self.vanished, self.failed_until = 0, 0, [], -1.0
        self.streams: list[tuple[int, int, int]] = []  # (observation's t, chunk's first t, delay)
        self.calls: list[tuple[float, float]] = []  # (start, end) of every call
        self.connect(0.0)

    def at(self, when: float, kind: str, data=None) -> None:
        self.order += 1
        heapq.heappush(self.events, (when, self.order, kind, data))

    def connect(self, now: float) -> None:
        """A new client (a new robot process): Ready, then its policy instructions."""
        self.client += 1
        self.peer, self.policy = (
            Peer(f"robot-{self.client}"),
            CodedStream(self.log, self.clock, self.max_delay),
        )
        self.rpc("Ready", lambda s: s._reset_server())
        self.rpc("SendPolicyInstructions", self.install)
        self.new_episode(now)

    def install(self, session) -> None:
        session.policy, session.policy_type, session.actions_per_chunk = self.policy, "sdp", 2 * TB
        session.lerobot_features, session.preprocessor = self.features, split_state
        session.postprocessor = lambda action: action

    def new_episode(self, now: float) -> None:
        self.queue, self.latest, self.must_go, self.chunk_size = {}, -1, True, -1
        self.busy, self.idle_run, self.sent_after_start = False, 0, False
        self.log.new_episode(now)

    def rpc(self, method: str, call):
        """One call through the service's session bookkeeping, as `SDPPolicyServer.call` does it."""
        session = self.service.session(self.peer, method)
        try:
            return call(session)
        finally:
            session.in_flight -= 1
            session.last_seen = self.clock()

    def run(self) -> "AsyncRun":
        for i, step in enumerate(self.steps):
            self.at(i * DT + step.jitter * DT, "tick", i)
        timeout = self.service.config.session_timeout_s
        sweeps = int(len(self.steps) * DT / (timeout / 4)) + 2
        for k in range(1, sweeps):
            self.at(k * timeout / 4, "sweep")
        while self.events:
            self.clock.now, _, kind, data = heapq.heappop(self.events)
            getattr(self, kind)(data)
            self.check_sessions()
        return self

    def tick(self, i: int) -> None:
        step = self.steps[i]
        if step.event:
            self.event(step.event)
        if self.queue:  # RobotClient.control_loop_action: the lowest timestep runs
            t = min(self.queue)
            self.log.run(self.queue.pop(t), i)
            self.latest, self.idle_run = t, 0
        else:
            self.idle_run += 1
            self.check_idle(i)
        if self.chunk_size < 0 or len(self.queue) / self.chunk_size <= 0.5:
            must_go = self.must_go and not self.queue
            # the robot moves as it acts and holds still while it waits (LeRobot's "too similar" filter)
            raw = {k: float(200 + j) for j, k in enumerate(self.keys)} | {"agent_x.pos": 10.0 * self.latest}
            obs = TimedObservation(self.clock(), max(self.latest, 0), raw, must_go)
            self.sent_after_start = self.sent_after_start or obs.get_timestep() > 0
            self.rpc("SendObservations", lambda s: s._enqueue_observation(obs))
            self.must_go = self.must_go and not must_go
        self.get_actions(step)

    def get_actions(self, step: Step) -> None:
        """RobotClient's receive thread: one GetActions at a time, answered once an observation waits."""
        session = self.service.sessions.get(f"id:{self.peer.client_id}")
        if self.busy or session is None or session.observation_queue.empty():
            return
        start, plan = self.clock(), session.plan
        self.policy.latency, self.policy.fail = step.latency, step.fail
        delay, streamed = session.delay_ticks(), len(self.policy.committed)
        try:
            reply = self.rpc("GetActions", lambda s: s.GetActions(None, self.peer))
        except self.server_mod.ClientError:
            reply = None
        end = max(self.clock(), start + 0.002)
        if reply is None:
            self.failed_until = end
        self.clock.now = start  # the client's ticks during the call run next, at their own times
        self.calls.append((start, end))
        if len(self.policy.committed) > streamed and session.plan is not plan:
            self.streams.append((session.current.get_timestep(), session.plan.end - TB, delay))
            self.check_stream()
        self.busy = True
        self.at(end, "receive", (reply, self.client, self.log.episode_start))

    def receive(self, data) -> None:
        reply, client, episode = data
        self.busy = False
        if client != self.client or episode != self.log.episode_start:
            return  # a reply to a client or an episode that is gone
        actions = [] if reply is None or not reply.data else pickle_loads(reply.data)
        if actions:
            self.chunk_size = max(self.chunk_size, len(actions))
            for a in actions:  # RobotClient._aggregate_action_queues, weighted_average
                t = a.get_timestep()
                if t > self.latest:
                    old = self.queue.get(t)
                    self.queue[t] = a.get_action() if old is None else 0.3 * old + 0.7 * a.get_action()
            self.must_go = True
        session = self.service.sessions.get(f"id:{self.peer.client_id}")
        if session is not None and not session.observation_queue.empty():
            self.get_actions(self.steps[min(int(self.clock() / DT), len(self.steps) - 1)])

    def event(self, kind: str) -> None:
        now = self.clock()
        if kind == "ready":  # the client starts a new episode as LeRobot's does: Ready first
            self.rpc("Ready", lambda s: s._reset_server())
            self.new_episode(now)
        elif kind == "restart" and self.sent_after_start:  # starts over without Ready (a restarted loop)
            self.new_episode(now)
        elif kind == "reconnect":  # a new connection, the same id: the same session
            self.peer = Peer(self.peer.client_id)
        elif kind == "vanish":  # this client is gone for good; a new one connects
            key = f"id:{self.peer.client_id}"
            session = self.service.sessions.get(key)
            self.vanished.append((key, max(now, session.last_seen if session else now)))
            self.connect(now)

    def sweep(self, _=None) -> None:
        self.service.sweep()

    def check_stream(self) -> None:
        t, first, delay = self.streams[-1]
        if first > t + 1 + delay:
            raise InvariantError(
                f"the chunk for observation {t} starts at {first}, more than {delay} + 1 after it"
            )

    def check_idle(self, tick: int) -> None:
        """Since the last failed call ended (if it did during this wait), the robot waits at most what
        the calls in flight take, and two ticks for the loop's phase and the client's next send."""
        since = max(self.clock() - self.idle_run * DT, min(self.failed_until, self.clock()))
        waited = round((self.clock() - since) / DT)
        busy_s = sum(
            min(end, self.clock()) - max(start, since - DT) for start, end in self.calls if end > since - DT
        )
        if waited > math.ceil(busy_s / DT) + 2:
            raise InvariantError(f"tick {tick}: the robot waited {waited} ticks, calls took {busy_s:.2f} s")

    def check_sessions(self) -> None:
        limit = self.service.config.session_timeout_s * 1.25 + 1e-9
        for key, since in self.vanished:
            if self.clock() > since + limit and key in self.service.sessions:
                raise InvariantError(
                    f"the session of {key} outlived its client by {self.clock() - since:.2f} s"
                )


def pickle_loads(data: bytes):
    import pickle  # nosec: the server's own reply, in this process

    return pickle.loads(data)


# ----------------------------------------------------------------------------------------------------
# RTC: SDPPolicy._rtc_chunk under LeRobot's RTC engine loop and ActionQueue
# ----------------------------------------------------------------------------------------------------


def small_sdp(max_delay: int):
    """A small SDP policy with pusht_sim's features (its denoiser is replaced by a coded stream)."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_sdp import SDPConfig, SDPPolicy

    inputs = {
        OBS_STATE: PolicyFeature(FeatureType.STATE, (2,)),
        OBS_ENV_STATE: PolicyFeature(FeatureType.ENV, (16,)),
    }
    config = SDPConfig(
        down_dims=(8, 16),
        diffusion_step_embed_dim=8,
        n_action_steps=TB,
        n_chunks=2,
        num_inference_steps=4,
        max_delay=max_delay,
        device="cpu",
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
    )
    return SDPPolicy(config).eval()


class RTCRun:
    """One schedule: `lerobot-rollout --inference.type=rtc` at 10 Hz. Its loop: each tick publishes the
    frame and pops the next action. Its thread: every 10 ms, once at most K actions are left, it calls
    the policy with the left-over padded to the execution horizon, and at the call's end merges the
    result dropping ceil(latency / tick) actions (LeRobot's ActionQueue), or the actions that ran since
    the frame (`queue_class` from the upstream patch); after a failure it sleeps 0.5 s. With the
    patch, each chunk's first action runs right after the rest of the last chunk (K + 1 ticks after
    its frame when the call took at most K), or on the first tick after the call if the rest ran out."""

    def __init__(self, steps: list[Step], k: int, policy, queue_class=ActionQueue):
        from lerobot.rollout.inference.rtc import _normalize_prev_actions_length

        self.pad = _normalize_prev_actions_length
        self.steps, self.k, self.clock, self.log = steps, k, Clock(), ActionLog()
        self.policy = policy
        policy.reset()
        self.stream = CodedStream(self.log, self.clock, policy.config.max_delay)
        policy._stream_step = self.coded_step
        self.rtc = RTCConfig(execution_horizon=TB + 2)
        self.queue, self.exact = queue_class(self.rtc), queue_class is not ActionQueue
        self.log.lenient = not self.exact
        self.times = [i * DT + s.jitter * DT for i, s in enumerate(steps)]
        self.frame_tick, self.latencies, self.pending = -1, [], None
        self.expected: dict[tuple[int, int], int] = {}  # a chunk's first action -> the tick it must run
        self.frame = {k_: torch.zeros(1, *ft.shape) for k_, ft in policy.config.input_features.items()}

    def coded_step(self, history, generator, compiled, committed=0):
        """SDPPolicy._stream_step's stand-in, keeping the buffer's own bookkeeping."""
        buffer = self.policy._buffer
        if buffer.sample is None:
            self.stream.reset()
            buffer.sample = torch.zeros(1, 1, 1)
        buffer.last_chunk = self.stream.chunk(committed)
        return buffer.last_chunk

    def run(self) -> "RTCRun":
        thread_at = 0.0
        for i, step in enumerate(self.steps):
            while thread_at < self.times[i]:  # the thread's turns before this tick
                thread_at = self.thread(thread_at)
            self.tick(i, step)
        return self

    def tick(self, i: int, step: Step) -> None:
        if step.event == "reset":  # the next episode: engine.reset() (policy, queue)
            self.policy.reset()
            self.queue.clear()
            self.log.new_episode(self.times[i])
            self.frame_tick = -1
        self.frame_tick = i
        action = self.queue.get()
        if action is not None:
            self.log.run(action, i)
            code = tuple(round(float(v)) for v in action)
            if code in self.expected and self.expected.pop(code) != i:
                raise InvariantError(f"tick {i}: chunk {code} ran late or early")

    def thread(self, now: float) -> float:
        """One turn of the RTC thread at `now`; returns when its next turn starts."""
        if self.pending is not None:
            return self.merge(now)
        if self.queue.qsize() > self.k or self.frame_tick < 0:
            return now + POLL_S
        step = self.steps[min(int(now / DT), len(self.steps) - 1)]
        left = self.queue.get_left_over()
        padded = None if left is None else self.pad(left, target_steps=self.rtc.execution_horizon)
        delay = math.ceil(max(self.latencies) / DT) if self.latencies else 0
        self.stream.latency, self.stream.fail, self.clock.now = step.latency, step.fail, now
        try:
            result = self.policy.predict_action_chunk(
                self.frame, inference_delay=delay, prev_chunk_left_over=padded
            )
        except RuntimeError:
            return now + step.latency + RETRY_S
        n_left = 0 if left is None else len(left)
        self.pending = (
            now + step.latency,
            result,
            self.queue.get_action_index(),
            self.frame_tick,
            n_left,
            step.latency,
            self.log.episode_start,
        )
        return now + step.latency

    def merge(self, now: float) -> float:
        end, result, index_before, frame, n_left, latency, episode = self.pending
        if end > now:
            return end
        self.pending = None
        self.latencies.append(latency)
        if episode != self.log.episode_start:  # a reset ran meanwhile: SDP refused the stale call
            return now
        self.queue.merge(result[0], result[0], math.ceil(latency / DT), index_before)
        if self.exact:  # the chunk's first action runs once the rest has, or at once if it ran out
            next_tick = next((i for i, t in enumerate(self.times) if t >= end), len(self.times))
            first = tuple(round(float(v)) for v in result[0, 1 + n_left])
            self.expected[first] = max(frame + 1 + n_left, next_tick)
        return now


def run_schedule(engine: str, steps: list[Step], variant: dict) -> dict:
    """Run one schedule; the counts of what ran, or a `InvariantError`."""
    with quiet("policy_server", "lerobot_sdp.policy_server", "lerobot.policies.rtc.action_queue"):
        return _run_schedule(engine, steps, variant)


@contextlib.contextmanager
def quiet(*names: str):
    """Thousands of calls a second: the servers' per-call INFO lines and the queue's delay warnings off."""
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def _run_schedule(engine: str, steps: list[Step], variant: dict) -> dict:
    if engine == "async":
        run = AsyncRun(steps, variant["max_delay"]).run()
        return {"executed": run.log.executed, "streams": len(run.streams), "calls": len(run.calls)}
    run = RTCRun(steps, variant["k"], variant["policy"], variant.get("queue_class", ActionQueue)).run()
    return {"executed": run.log.executed, "repeated": run.log.repeated, "skipped": run.log.skipped}


def schedule_summary(steps: list[Step]) -> list[dict]:
    return [{"tick": i, **asdict(s)} for i, s in enumerate(steps) if s != Step()]


def patched_action_queue(patch: Path, workdir: Path) -> type:
    """LeRobot's ActionQueue with `patch` (docs/upstream/lerobot-0.6.1-rtc-actions-run.patch) applied
    to a copy of the installed file under `workdir`, imported as a module of its own."""
    import lerobot.policies.rtc.action_queue as installed

    target = workdir / "src" / "lerobot" / "policies" / "rtc" / "action_queue.py"
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(installed.__file__, target)
    done = subprocess.run(
        ["patch", "-p1", "--forward", "-i", str(patch.resolve())], cwd=workdir, capture_output=True
    )
    if done.returncode:
        raise ValueError(f"{patch} does not apply to the installed LeRobot: {done.stdout.decode()}")
    name = "lerobot.policies.rtc._action_queue_patched"
    spec = importlib.util.spec_from_file_location(name, target)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.ActionQueue


# ----------------------------------------------------------------------------------------------------
# lerobot-sdp-bench schedules
# ----------------------------------------------------------------------------------------------------

PATCH = Path(__file__).resolve().parents[2] / "docs" / "upstream" / "lerobot-0.6.1-rtc-actions-run.patch"


def variants(patched: type | None) -> dict[str, tuple[str, dict]]:
    """The engines and settings each schedule runs under."""
    out = {f"async, max_delay {d}": ("async", {"max_delay": d}) for d in (0, 3)}
    for k, max_delay in ((0, 0), (1, 3), (2, 3)):
        policy = small_sdp(max_delay)
        out[f"rtc K={k}, LeRobot's ActionQueue"] = (
            "rtc",
            {"k": k, "policy": policy, "queue_class": ActionQueue},
        )
        if patched is not None:
            out[f"rtc K={k}, patched ActionQueue"] = (
                "rtc",
                {"k": k, "policy": policy, "queue_class": patched},
            )
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--schedules", type=int, default=1000, help="random schedules per engine setting")
    p.add_argument("--seed", type=int, default=0, help="schedule i is drawn from seed + i")
    p.add_argument("--ticks", type=int, default=240, help="control ticks per schedule (10 Hz)")
    p.add_argument("--patch", type=Path, default=PATCH, help="the upstream ActionQueue patch ('' for none)")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/schedules"))


def run(args: argparse.Namespace) -> None:
    import tempfile
    import time

    from .report import write_json

    args.output_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        patched = patched_action_queue(args.patch, Path(tmp)) if str(args.patch) else None
    results = {
        "command": " ".join(sys.argv),
        "seeds": [args.seed, args.seed + args.schedules - 1],
        "ticks": args.ticks,
    }
    for name, (engine, variant) in variants(patched).items():
        start, totals, failures = time.perf_counter(), {}, []
        for seed in range(args.seed, args.seed + args.schedules):
            steps = random_schedule(random.Random(seed), engine, args.ticks)
            try:
                counts = run_schedule(engine, steps, variant)
            except InvariantError as e:
                failures.append({"seed": seed, "error": str(e)})
                continue
            totals = {k: totals.get(k, 0) + v for k, v in counts.items()}
        results[name] = {**totals, "failed": failures, "seconds": round(time.perf_counter() - start, 1)}
        logging.info("%s: %s", name, results[name])
        write_json(args.output_dir / "results.json", results)
