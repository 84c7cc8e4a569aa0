"""`lerobot-sdp-policy-server`: LeRobot's async-inference `PolicyServer` with SDP accepted, one session
per client.

LeRobot 0.6.1's `python -m lerobot.async_inference.policy_server` never imports third-party plugins,
accepts only the policy types in `async_inference.constants.SUPPORTED_POLICIES`, and holds one policy
and one observation queue for whoever connected last. This command imports the plugin, adds `sdp` to
that list, and gives every client (gRPC peer) its own LeRobot `PolicyServer` (`ClientPolicyServer`):
its own policy, observation queue, history and SDP buffer, so a client that misbehaves or disappears
does not disturb the others. Idle sessions are dropped after `--session_timeout_s`.

What a broken or hostile client cannot do (docs/deployment.md, "Threat model and limits"):
- **Run code here.** Client bytes are read with `protocol_pickle.loads` (LeRobot's message types only),
  never plain `pickle.loads`; the server listens on localhost unless `--host` says otherwise.
- **Poison its history.** An observation is checked (keys, shapes, finite numbers, an int timestep)
  before it is stored; a refused one leaves no trace, and the error names the value and the fix.
- **Take every thread.** At most `--max_calls_per_client` calls per client and `--max_clients`
  clients; an upload larger than `--max_observation_mb` or unfinished after `--receive_timeout_s` is
  cut off; the thread pool has room for every client's calls. A dropped session frees its policy.
- **Lose its session on a reconnect.** A client is known by its `x-sdp-client-id` (or
  `x-lerobot-client-id`) gRPC metadata when it sends one, else by its connection; a call that needs a
  policy the server does not hold for that client is refused with FAILED_PRECONDITION saying to send
  Ready and the policy instructions again.

What SDP needs on top of LeRobot's server (docs/deployment.md, "Async inference"):
- **History, per client.** LeRobot's server calls `predict_action_chunk` on the one observation it
  runs. Every observation a client sends (also those the server does not run) is kept by its control
  timestep, and the policy conditions on the frames of the last `n_obs_steps` timesteps; a timestep
  that was never sent repeats the next newer frame, as LeRobot pads a history at an episode's start.
- **The buffer follows what the robot executed.** The client stamps an observation with the timestep
  of its last executed action, t, and times the reply's action i at t + i (it drops those <= t). The
  server keeps the plan it sent (`Plan`, normalised actions by timestep); the buffer's next chunk
  begins where the plan ends. A reply is the plan's unexecuted rest followed by one streamed chunk
  (N/h denoiser calls), so the buffer advances one chunk per chunk the robot can execute, whatever
  the number of actions executed between two calls. A timestep lower than the newest one received
  is a new episode (the client started over without Ready): the history, the plan and the stream
  restart, and an observation of the old episode still queued is dropped.
- **On time.** A chunk streams only once at most `delay_ticks` unexecuted actions are left (the
  inference delay in control ticks: `--delay_ticks`, or measured from the server's own inference
  times: from the observation's arrival to its reply, pickled, the first chunk of a stream left out,
  as it primes and may warm up; never a whole chunk), so that it arrives as the rest runs out;
  before that the reply is the rest alone, without a denoiser call. A policy trained with
  `max_delay` denoises the chunk with that rest as committed slots
  (`SDPPolicy.predict_action_chunk(committed=...)`): the observation of tick t conditions a chunk
  that starts at t + 1 + rest, as in training. A policy trained without it denoises the chunk
  as if it started right after the observation, at most `delay_ticks` ticks early.
"""

import logging
import math
import pickle  # nosec: only to re-encode messages already read with protocol_pickle
import threading
import time
from collections import deque
from concurrent import futures
from dataclasses import dataclass, field
from typing import Any

import draccus
import grpc
import numpy as np
import torch
from lerobot.async_inference.configs import PolicyServerConfig
from lerobot.async_inference.constants import SUPPORTED_POLICIES
from lerobot.async_inference.helpers import (
    RemotePolicyConfig,
    TimedObservation,
    raw_observation_to_observation,
)
from lerobot.async_inference.policy_server import PolicyServer
from lerobot.configs.policies import PreTrainedConfig
from lerobot.transport import services_pb2, services_pb2_grpc
from lerobot.transport.utils import MAX_MESSAGE_SIZE
from lerobot.utils.constants import OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor

import lerobot_sdp  # noqa: F401  (registers `sdp` and `pusht_sim`)
from lerobot_sdp import protocol_pickle

if "sdp" not in SUPPORTED_POLICIES:  # the list LeRobot's server checks, extended in place
    SUPPORTED_POLICIES.append("sdp")

logger = logging.getLogger(__name__)
FRAMES_KEPT = 16  # received observations kept per client for the history (control timesteps)
LATENCIES_KEPT = 8  # the delay estimate is the slowest of the last few chunks
SWEEPS_PER_TIMEOUT = 4  # idle sessions are dropped at most a quarter of the timeout late
# gRPC metadata that names a client across reconnects (ours; the one proposed to LeRobot's client)
CLIENT_ID_KEYS = ("x-sdp-client-id", "x-lerobot-client-id")
NEEDS_POLICY = ("SendObservations", "GetActions")
LOOPBACK = ("localhost", "127.0.0.1", "::1")
TransferState = services_pb2.TransferState


@dataclass
class SDPPolicyServerConfig(PolicyServerConfig):
    max_clients: int = field(default=4, metadata={"help": "Clients served at once (one policy each)"})
    session_timeout_s: float = field(
        default=30.0, metadata={"help": "Drop a client's session after this long without a call"}
    )
    delay_ticks: int | None = field(
        default=None,
        metadata={
            "help": "Stream a chunk once at most this many unexecuted actions are left (the inference "
            "delay in control ticks); default: measured, the slowest of the last chunks at --fps"
        },
    )

    max_calls_per_client: int = field(
        default=4,
        metadata={"help": "Calls one client may have running at once (LeRobot's RobotClient uses 2)"},
    )
    max_observation_mb: float = field(
        default=16.0, metadata={"help": "Largest observation a client may upload, in MiB (all its chunks)"}
    )
    receive_timeout_s: float = field(
        default=5.0,
        metadata={"help": "Cancel an observation upload not finished after this long (a stalled client)"},
    )

    def __post_init__(self):
        super().__post_init__()
        for name in ("max_clients", "max_calls_per_client"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("session_timeout_s", "max_observation_mb", "receive_timeout_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.delay_ticks is not None and self.delay_ticks < 0:
            raise ValueError(f"delay_ticks must be at least 0 (or unset: measured), got {self.delay_ticks}")


@dataclass
class Plan:
    """The normalised actions (1, L, A) sent to a client for control timesteps start .. start + L - 1,
    in the session's `episode`. The SDP buffer's next chunk begins at `end`."""

    start: int
    actions: Tensor
    episode: int = 0

    @property
    def end(self) -> int:
        return self.start + self.actions.shape[1]


def policy_problem(specs: Any) -> str | None:
    """Why a client's policy instructions cannot be served, or None."""
    if not isinstance(specs, RemotePolicyConfig):
        return f"Policy instructions must be a RemotePolicyConfig, got {type(specs).__name__}."
    path = specs.pretrained_name_or_path
    try:
        config = PreTrainedConfig.from_pretrained(path)
    except Exception as e:  # a missing folder, an offline Hub id, a broken config.json
        return f"Cannot read a policy config from {path!r}: {e}"
    if config.type != specs.policy_type:
        return (
            f"{path!r} holds a `{config.type}` policy, and the client asked for `{specs.policy_type}`: "
            f"start the client with --policy_type={config.type}, or point it at a `{specs.policy_type}` "
            "checkpoint."
        )
    if config.type not in SUPPORTED_POLICIES:
        return f"Policy type `{config.type}` is not served; this server serves {SUPPORTED_POLICIES}."
    return feature_problem(config, specs.lerobot_features) if config.type == "sdp" else None


def feature_problem(config: PreTrainedConfig, robot_features: dict[str, dict]) -> str | None:
    """Whether the client's robot observations can feed this SDP policy (state, split state, cameras)."""
    state = robot_features.get(OBS_STATE)
    sent = state["shape"][0] if state else 0
    parts = {
        k: config.input_features[k].shape[0] for k in (OBS_STATE, OBS_ENV_STATE) if k in config.input_features
    }
    if sent != sum(parts.values()):
        return (
            f"The robot sends `{OBS_STATE}` with {sent} values and the policy takes {sum(parts.values())} "
            f"({', '.join(f'{k}: {n}' for k, n in parts.items())}, joined in this order); use the robot "
            "the policy was trained for, or a policy trained on this robot's data."
        )
    missing = [k for k in config.image_features if k not in robot_features]
    if missing:
        cameras = [k for k in robot_features if k.startswith(OBS_IMAGES)]
        return f"The policy needs cameras {missing}; the robot has {cameras}."
    return None


def raw_observation_problem(raw: Any, robot_features: dict[str, dict]) -> str | None:
    """A missing, mis-shaped or non-finite value in a robot observation, named, or None (LeRobot's own
    conversion would fail with a bare KeyError or a shape error deep inside torch, or feed NaN on)."""
    if not isinstance(raw, dict):
        return f"An observation must be a dict of named values, got {type(raw).__name__}."
    for key, ft in robot_features.items():
        if ft["dtype"] in ("image", "video"):
            name = key.removeprefix(f"{OBS_IMAGES}.")
            value = raw.get(name)
            shape = tuple(getattr(value, "shape", ()))
            if value is None or shape != tuple(ft["shape"]):
                found = "missing" if value is None else f"of shape {shape}"
                return f"Observation `{name}` is {found}; expected an image of shape {tuple(ft['shape'])}."
            continue
        for name in ft["names"]:
            if name not in raw:
                declared = f"the robot declared {len(ft['names'])} values for `{key}`"
                return f"Observation is missing `{name}` ({declared})."
            problem = number_problem(name, raw[name])
            if problem:
                return problem
    return None


def number_problem(name: str, value: Any) -> str | None:
    """Why `value` is not one finite number, or None."""
    if getattr(value, "shape", ()) not in ((), (1,)):
        return f"Observation `{name}` has shape {tuple(value.shape)}; expected one number."
    try:
        number = float(np.asarray(value, dtype=np.float64).reshape(-1)[0])
    except (TypeError, ValueError):
        return f"Observation `{name}` is a {type(value).__name__}; expected a number."
    if not math.isfinite(number):
        return f"Observation `{name}` is {number} (NaN or inf); every value must be finite: check the sensor."
    return None


@dataclass
class EpisodeObservation(TimedObservation):
    """A client's observation as the session stores it: with the session's episode count when it
    arrived (an observation of an episode the client has left is never run) and the arrival time
    (the delay estimate counts from it)."""

    episode: int = 0
    received: float = 0.0


class StaleObservationError(Exception):
    """An observation of an episode the client has left: dropped, the client gets no reply for it."""


class ClientError(Exception):
    """A call the server refuses; the client receives `code` and the message."""

    code = grpc.StatusCode.INVALID_ARGUMENT


class BadObservationError(ClientError):
    """A robot observation with a missing, mis-shaped or non-finite value."""


class SessionError(ClientError):
    """A call that needs a policy this server does not hold for the client."""

    code = grpc.StatusCode.FAILED_PRECONDITION


class LimitError(ClientError):
    """A call past one of the server's limits."""

    code = grpc.StatusCode.RESOURCE_EXHAUSTED


def read_message(data: bytes, kind: type) -> Any:
    """A client message of type `kind`, read with the restricted unpickler."""
    try:
        message = protocol_pickle.loads(data)
    except protocol_pickle.UnsafePayloadError as e:
        raise ClientError(str(e)) from e
    if not isinstance(message, kind):
        raise ClientError(f"Expected a {kind.__name__}, got a {type(message).__name__}.")
    return message


def receive_upload(request_iterator, context, max_bytes: int, timeout_s: float) -> bytes:
    """One message of LeRobot's chunked upload (TRANSFER_BEGIN / MIDDLE / END), bounded in size and in
    time: after `timeout_s` the call is cancelled, which ends the wait for the next chunk and frees the
    thread (LeRobot's `receive_bytes_in_chunks` waits and collects without bound)."""
    timer = threading.Timer(timeout_s, context.cancel)
    timer.daemon = True
    timer.start()
    parts, size = [], 0
    try:
        for item in request_iterator:
            if item.transfer_state == TransferState.TRANSFER_BEGIN:
                parts, size = [], 0
            parts.append(item.data)
            size += len(item.data)
            if size > max_bytes:
                raise LimitError(
                    f"Observation upload over {max_bytes / 2**20:g} MiB; send smaller observations (fewer or "
                    "smaller camera images), or start the server with a higher --max_observation_mb."
                )
            if item.transfer_state == TransferState.TRANSFER_END:
                return b"".join(parts)
    finally:
        timer.cancel()
    raise ClientError("The observation upload ended before its TRANSFER_END chunk.")


class ClientPolicyServer(PolicyServer):
    """LeRobot's `PolicyServer` for one client. For SDP it keeps the client's observation history and
    `Plan` (module docstring); for any policy, a refused observation or setup reaches the client as an
    error with the reason, instead of a silent empty reply, and an observation is checked before
    anything keeps it."""

    def __init__(self, config: SDPPolicyServerConfig, clock=time.monotonic):
        super().__init__(config)
        self.clock = clock
        self.episode = 0  # counts the client's episodes: Ready, or its timestep going back
        self.retry = False  # the last prediction failed: the next observation goes through
        self.streamed_from: float | None = None  # arrival of the observation whose reply streams
        self.frames: dict[int, TimedObservation] = {}
        self.frames_lock = threading.Lock()  # SendObservations writes frames while GetActions reads them
        self.predict_lock = threading.Lock()  # one chunk at a time: the SDP buffer is one stream
        self.plan: Plan | None = None
        self.error: str | None = None
        self.current: TimedObservation | None = None
        self.last_seen = clock()
        self.in_flight = 0  # calls running now: a session is idle only with none
        self.latencies: deque[float] = deque(maxlen=LATENCIES_KEPT)  # seconds per streamed chunk

    def _reset_server(self) -> None:
        """Ready (a client starting over): every piece of per-episode state, LeRobot's and ours."""
        super()._reset_server()
        with self.frames_lock:
            self.frames = {}
            self.episode += 1
        self.plan, self.error, self.last_processed_obs, self.retry = None, None, None, False
        self.fps_tracker.reset()
        if self.policy is not None:
            self.policy.reset()

    def SendPolicyInstructions(self, request, context):  # noqa: N802 (gRPC's name)
        specs = read_message(request.data, RemotePolicyConfig)
        problem = policy_problem(specs)
        if problem:
            raise ClientError(problem)
        # LeRobot's handler unpickles request.data again: hand it bytes this server wrote
        request = services_pb2.PolicySetup(data=pickle.dumps(specs))
        return super().SendPolicyInstructions(request, context)

    def GetActions(self, request, context):  # noqa: N802 (gRPC's name)
        reply = super().GetActions(request, context)
        if self.error is not None:
            message, self.error = self.error, None
            raise ClientError(message)
        if self.streamed_from is not None:  # the whole reply: queue, processors, chunk, pickling
            self.latencies.append(self.clock() - self.streamed_from)
            self.streamed_from = None
        return reply

    def SendObservations(self, request_iterator, context):  # noqa: N802 (gRPC's name)
        """LeRobot's handler, bounded: the upload through `receive_upload`, the bytes through the
        restricted unpickler, the observation checked before it is stored."""
        max_bytes = int(self.config.max_observation_mb * 2**20)
        try:
            data = receive_upload(request_iterator, context, max_bytes, self.config.receive_timeout_s)
        except grpc.RpcError:  # cancelled: the upload stalled, or the client went away
            logger.warning(
                "An observation upload did not finish within %.1f s (--receive_timeout_s): cancelled.",
                self.config.receive_timeout_s,
            )
            return services_pb2.Empty()
        self._enqueue_observation(read_message(data, TimedObservation))
        return services_pb2.Empty()

    def _enqueue_observation(self, obs: TimedObservation) -> bool:
        t = obs.get_timestep()
        problem = raw_observation_problem(obs.get_observation(), self.lerobot_features)
        if not isinstance(t, int):
            problem = (
                f"the timestep is a {type(t).__name__}; LeRobot's protocol counts control ticks in ints."
            )
        if problem:  # checked before anything keeps it: a refused frame leaves no trace
            raise BadObservationError(f"Observation #{t}: {problem}")
        with self.frames_lock:
            restart = bool(self.frames) and t < max(self.frames)
            if restart:
                logger.info("Client timestep went back to %d: a new episode, the history restarts.", t)
                self.frames, self.last_processed_obs = {}, None
                self.episode += 1
            # after a failed prediction the client waits with an empty queue and sends the same state
            # again: it must go, or LeRobot's "too similar" filter drops it and the robot stalls for good
            must_go, self.retry = obs.must_go or self.retry, False
            obs = EpisodeObservation(obs.timestamp, t, obs.observation, must_go, self.episode, self.clock())
            self.frames[t] = obs
            for old in sorted(self.frames)[:-FRAMES_KEPT]:
                del self.frames[old]
        with self._predicted_timesteps_lock:  # LeRobot's set would grow for the whole session
            kept = () if restart else self._predicted_timesteps
            self._predicted_timesteps = {s for s in kept if s > t - FRAMES_KEPT}
        return super()._enqueue_observation(obs)

    def _predict_action_chunk(self, observation_t: EpisodeObservation):
        with self.predict_lock:
            self.current, self.streamed_from = observation_t, None
            try:
                if observation_t.episode != self.episode:
                    raise StaleObservationError(
                        f"Observation #{observation_t.get_timestep()} belongs to an episode the client has "
                        "left: dropped."
                    )
                return super()._predict_action_chunk(observation_t)
            except (ValueError, KeyError, RuntimeError, StaleObservationError) as e:  # LeRobot drops it
                if not isinstance(e, StaleObservationError):  # e.g. SDP refusing NaN, out of memory
                    self.error, self.retry = str(e), True
                with self._predicted_timesteps_lock:  # a corrected observation at this timestep may run
                    self._predicted_timesteps.discard(observation_t.get_timestep())
                raise

    def _get_action_chunk(self, observation: dict[str, Tensor]) -> Tensor:
        if self.policy_type != "sdp":
            return super()._get_action_chunk(observation)
        t, episode = self.current.get_timestep(), self.current.episode
        return self.sdp_reply(self._history(observation, t), t, episode)[:, : self.actions_per_chunk]

    def sdp_reply(self, history: dict[str, Tensor], t: int, episode: int = 0) -> Tensor:
        """The actions for timesteps t, t + 1, ...: the plan's unexecuted rest, then one streamed chunk
        once at most `delay_ticks()` of the rest are left to run. `episode`: the session's count of the
        client's episodes when the observation arrived."""
        plan, past_the_plan = self.plan, False
        if plan is not None and (episode != plan.episode or t < plan.start):
            logger.info("Client started a new episode at timestep %d: the stream restarts.", t)
            self.policy.reset()
            plan = None
        elif plan is not None and t >= plan.end:  # executed past what was sent: not LeRobot's client
            logger.warning(
                "Client executed up to %d, past the plan's end %d: the stream restarts.", t, plan.end - 1
            )
            self.policy.drop_queued_actions()
            plan, past_the_plan = None, True
        rest = plan.actions[:, t - plan.start :] if plan is not None else None
        left = 0 if rest is None else max(0, rest.shape[1] - 1)  # the action at t has run
        if left > self.delay_ticks():  # the chunk would run late: stream at a later observation
            return rest
        committed = left if self.policy.config.max_delay else 0
        chunk = self.policy.predict_action_chunk(history, committed=committed)
        if plan is not None:  # a stream's first chunk primes it (and may warm up): not its delay
            self.streamed_from = getattr(self.current, "received", None)
        if past_the_plan:  # the action at t has run: a slot for t, which the client drops, then the chunk
            rest = chunk[:, :1]
        actions = chunk if rest is None else torch.cat([rest, chunk], dim=1)
        self.plan = Plan(t, actions, episode)
        return actions

    def delay_ticks(self) -> int:
        """Unexecuted actions left at which a chunk streams: `--delay_ticks`, else the slowest recent
        chunk (at least LeRobot's `--inference_latency`, which the server pads every reply to) in control
        ticks; a whole chunk less one before the first measurement. At most `max_delay` for a policy
        trained with it (its chunk then starts right after the committed rest)."""
        config, policy_config = self.config, self.policy.config
        if config.delay_ticks is not None:
            ticks = config.delay_ticks
        elif self.latencies:  # never more than a chunk less one: a chunk streams at most once per chunk
            slowest = max(max(self.latencies), config.inference_latency)
            ticks = min(math.ceil(slowest * config.fps), policy_config.n_action_steps - 1)
        else:
            ticks = policy_config.n_action_steps - 1
        return min(ticks, policy_config.max_delay) if policy_config.max_delay else ticks

    def _history(self, current: dict[str, Tensor], t: int) -> dict[str, Tensor]:
        """(1, n_obs_steps, ...) per input feature, from the frames received for t - n_obs_steps + 1 .. t."""
        with self.frames_lock:
            past = [self.frames.get(k) for k in range(t - self.policy.config.n_obs_steps + 1, t)]
        frames = [current]
        for frame in reversed(past):
            frames.insert(0, self._process(frame) if frame is not None else frames[0])
        return {
            key: torch.stack([f[key] for f in frames], dim=1) for key in self.policy.config.input_features
        }

    def _process(self, frame: TimedObservation) -> dict[str, Tensor]:
        raw = frame.get_observation()
        return self.preprocessor(
            raw_observation_to_observation(raw, self.lerobot_features, self.policy_image_features)
        )


class SDPPolicyServer(services_pb2_grpc.AsyncInferenceServicer):
    """The gRPC service: routes each call to its client's `ClientPolicyServer`, within the limits."""

    def __init__(self, config: SDPPolicyServerConfig, clock=time.monotonic):
        self.config, self.clock = config, clock
        self.sessions: dict[str, ClientPolicyServer] = {}
        self._lock = threading.Lock()
        self._closed = threading.Event()

    def sweep(self) -> None:
        """Drop the sessions idle for longer than `--session_timeout_s`."""
        with self._lock:
            self._drop_idle(self.clock())

    def start_sweeping(self) -> threading.Thread:
        """Sweep in a thread, a few times per timeout, until `close()`: a session whose client
        vanished is dropped, and its policy freed, even when no other call ever comes."""
        period = self.config.session_timeout_s / SWEEPS_PER_TIMEOUT

        def sweep_until_closed():
            while not self._closed.wait(period):
                try:
                    self.sweep()
                except Exception:  # a session that fails to stop must not end the sweeping
                    logger.exception("Sweeping idle sessions failed; sweeping goes on.")

        thread = threading.Thread(target=sweep_until_closed, name="sdp-session-sweeper", daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        """Stop sweeping and drop every session."""
        self._closed.set()
        with self._lock:
            for key in list(self.sessions):
                self.sessions.pop(key).stop()

    @staticmethod
    def client_key(context) -> str:
        """The client's id metadata (the same across reconnects), else its connection."""
        for key, value in context.invocation_metadata() or ():
            if key in CLIENT_ID_KEYS and value:
                return f"id:{value[:128]}"
        return context.peer()

    def session(self, context, method: str) -> ClientPolicyServer:
        key, now = self.client_key(context), self.clock()
        with self._lock:
            self._drop_idle(now)
            session = self.sessions.get(key)
            if method in NEEDS_POLICY and (session is None or session.policy is None):
                raise SessionError(
                    f"This server holds no policy for this client ({key}): it has not sent its policy "
                    "instructions, reconnected from a new address without `x-sdp-client-id` metadata, "
                    f"was dropped after {self.config.session_timeout_s:g} s without a call "
                    "(--session_timeout_s), or the server restarted. Send Ready and the policy instructions "
                    "again (LeRobot's RobotClient: restart it)."
                )
            if session is None:
                if len(self.sessions) >= self.config.max_clients:
                    raise LimitError(
                        f"This server already serves {len(self.sessions)} clients (--max_clients="
                        f"{self.config.max_clients}); retry later or start it with a higher --max_clients."
                    )
                session = self.sessions[key] = ClientPolicyServer(self.config, self.clock)
            elif session.in_flight >= self.config.max_calls_per_client:
                raise LimitError(
                    f"This client already has {session.in_flight} calls running (--max_calls_per_client="
                    f"{self.config.max_calls_per_client}); LeRobot's RobotClient needs 2: wait for a reply."
                )
            session.last_seen = now
            session.in_flight += 1
        return session

    def _drop_idle(self, now: float) -> None:
        idle = self.config.session_timeout_s
        for gone in [k for k, s in self.sessions.items() if not s.in_flight and now - s.last_seen > idle]:
            logger.info(
                "Dropping the session of %s (no call for %.0f s).", gone, now - self.sessions[gone].last_seen
            )
            self.sessions.pop(gone).stop()  # nothing else holds it: its policy is freed with it

    def call(self, method: str, request, context):
        """Run one RPC in its client's session; the session counts as busy until the call returns (a
        chunk slower than `--session_timeout_s` on a loaded machine does not get it dropped). A refused
        call reaches the client as its `ClientError` code and message."""
        try:
            session = self.session(context, method)
        except ClientError as e:
            context.abort(e.code, str(e))
        try:
            return getattr(session, method)(request, context)
        except ClientError as e:
            context.abort(e.code, str(e))
        finally:
            with self._lock:
                session.in_flight -= 1
                session.last_seen = self.clock()

    def Ready(self, request, context):  # noqa: N802 (gRPC's names, from here on)
        return self.call("Ready", request, context)

    def SendPolicyInstructions(self, request, context):  # noqa: N802
        return self.call("SendPolicyInstructions", request, context)

    def SendObservations(self, request_iterator, context):  # noqa: N802
        return self.call("SendObservations", request_iterator, context)

    def GetActions(self, request, context):  # noqa: N802
        return self.call("GetActions", request, context)


def worker_threads(config: SDPPolicyServerConfig) -> int:
    """Every client's calls at once, and a few to refuse the calls past the limits with."""
    return config.max_clients * config.max_calls_per_client + 4


def start_server(config: SDPPolicyServerConfig) -> tuple[grpc.Server, SDPPolicyServer, int]:
    """Start the service on `config.host:config.port`; returns the bound port."""
    service = SDPPolicyServer(config)
    workers = worker_threads(config)
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=workers),
        maximum_concurrent_rpcs=workers,  # calls past it are refused by gRPC, never queued behind a stall
        options=[("grpc.max_receive_message_length", MAX_MESSAGE_SIZE)],  # one chunk of LeRobot's uploads
    )
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(service, server)
    port = server.add_insecure_port(f"{config.host}:{config.port}")
    server.start()
    service.start_sweeping()
    return server, service, port


@draccus.wrap()
def serve(config: SDPPolicyServerConfig) -> None:
    server, service, port = start_server(config)
    logger.info("SDP policy server on %s:%d (policies: %s)", config.host, port, ", ".join(SUPPORTED_POLICIES))
    if config.host not in LOOPBACK:
        logger.warning(
            "Listening on %s: anyone who can reach port %d can load any policy this machine can read and "
            "drive its CPU or GPU; there is no authentication (docs/deployment.md, threat model).",
            config.host,
            port,
        )
    try:
        server.wait_for_termination()
    finally:
        service.close()


def main() -> None:
    serve()
