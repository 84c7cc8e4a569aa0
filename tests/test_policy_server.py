"""`lerobot-sdp-policy-server`: LeRobot's async PolicyServer with SDP, one session per client; the plan
and history that keep SDP's buffer in step with what the robot executed; faults reach the client."""

import json
import logging
import math
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import torch
from sdp_test_utils import PUSHT_KEYPOINT_STATS, history, save_tiny_policy, tiny_config

from lerobot_sdp.lerobot_cli import let_sigint_reach_children

TB = 4  # tiny_config's n_action_steps


def pusht_features(tmp_path) -> dict:
    from lerobot.async_inference.helpers import map_robot_keys_to_lerobot_features
    from lerobot.robots.utils import make_robot_from_config

    from lerobot_sdp.robots import PushTSimConfig

    robot = make_robot_from_config(PushTSimConfig(calibration_dir=tmp_path / "calibration"))
    return map_robot_keys_to_lerobot_features(robot)


def raw_observation(agent_x: float = 100.0) -> dict:
    from lerobot_sdp.robots.pusht_sim import AGENT_KEYS, KEYPOINT_KEYS

    values = {key: 200.0 + i for i, key in enumerate(AGENT_KEYS + KEYPOINT_KEYS)}
    return {**values, "agent_x.pos": agent_x, "task": ""}


def session_with(server_mod, policy, tmp_path=None, actions_per_chunk: int = 100, **config):
    """A ClientPolicyServer holding `policy`, as SendPolicyInstructions would leave it."""
    from lerobot_sdp import make_sdp_pre_post_processors

    session = server_mod.ClientPolicyServer(server_mod.SDPPolicyServerConfig(**config))
    session.policy, session.policy_type, session.actions_per_chunk = policy, "sdp", actions_per_chunk
    session.preprocessor, session.postprocessor = make_sdp_pre_post_processors(
        policy.config, PUSHT_KEYPOINT_STATS
    )
    if tmp_path is not None:
        session.lerobot_features = pusht_features(tmp_path)
    return session


def twin_policies(**overrides):
    """Two SDP policies with the same weights: the server's, and a reference streamed by hand."""
    from lerobot_sdp import SDPPolicy

    torch.manual_seed(0)
    served = SDPPolicy(tiny_config(**overrides)).eval()
    reference = SDPPolicy(tiny_config(**overrides)).eval()
    reference.load_state_dict(served.state_dict())
    return served, reference


def counted(policy) -> list:
    """Record every streaming call (predict_action_chunk) the policy makes."""
    calls, original = [], policy.predict_action_chunk

    def wrapper(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    policy.predict_action_chunk = wrapper
    return calls


def test_reply_is_the_unexecuted_plan_then_one_streamed_chunk(server_mod):
    """The buffer advances one chunk per reply that streams; the reply's head is what the robot has
    not executed yet; more than `delay_ticks` (here 3) still ahead of the robot means no denoiser call."""
    served, reference = twin_policies()
    session = session_with(server_mod, served, delay_ticks=TB - 1)
    calls = counted(served)
    obs = history(served.config, batch_size=1)

    torch.manual_seed(1)
    first = session.sdp_reply(obs, 0)
    torch.manual_seed(1)
    assert torch.allclose(first, reference.predict_action_chunk(obs))
    assert first.shape == (1, TB, 2) and (session.plan.start, session.plan.end) == (0, TB)

    # The robot executed actions 0..2 of 0..3: the reply is actions 2..3 again, then the next chunk.
    torch.manual_seed(2)
    second = session.sdp_reply(obs, 2)
    torch.manual_seed(2)
    assert torch.equal(second[:, :2], first[:, 2:])
    assert torch.allclose(second[:, 2:], reference.predict_action_chunk(obs))
    assert (session.plan.start, session.plan.end) == (2, 2 + 2 + TB) and len(calls) == 2

    # One more action executed: 4 of the plan's actions are still ahead, more than 3: no denoising.
    third = session.sdp_reply(obs, 3)
    assert torch.equal(third, second[:, 1:]) and len(calls) == 2 and session.plan.start == 2

    # Two more: 3 ahead, so one more chunk streams after them, continuing the reference stream.
    torch.manual_seed(3)
    fourth = session.sdp_reply(obs, 5)
    torch.manual_seed(3)
    assert torch.equal(fourth[:, :3], second[:, 3:])
    assert torch.allclose(fourth[:, 3:], reference.predict_action_chunk(obs))
    assert (session.plan.start, session.plan.end) == (5, 2 + 2 + 2 * TB)

    # At the plan's last action: nothing to resend but the one the client drops, the stream goes on.
    torch.manual_seed(5)
    fifth = session.sdp_reply(obs, session.plan.end - 1)
    torch.manual_seed(5)
    assert torch.equal(fifth[:, :1], fourth[:, -1:])
    assert torch.allclose(fifth[:, 1:], reference.predict_action_chunk(obs)) and len(calls) == 4


@pytest.mark.parametrize("jump", ["back", "at_the_plans_end", "past_the_plan"])
def test_stream_restarts_when_the_timestep_leaves_the_plan(server_mod, jump):
    """A timestep before the plan (a new episode) or past its end restarts the stream from the primer."""
    served, reference = twin_policies()
    session = session_with(server_mod, served, delay_ticks=TB - 1)
    obs = history(served.config, batch_size=1)
    session.sdp_reply(obs, 10)
    session.sdp_reply(obs, 12)
    t = {"back": 0, "at_the_plans_end": session.plan.end, "past_the_plan": session.plan.end + 3}[jump]
    torch.manual_seed(4)
    restarted = session.sdp_reply(obs, t)
    torch.manual_seed(4)
    first = reference.predict_action_chunk(obs)  # the reference's first chunk
    # back: a new episode, nothing ran yet; past the plan: the action at t ran, the client drops slot t
    slot = 0 if jump == "back" else 1
    assert torch.allclose(restarted[:, slot:], first) and restarted.shape[1] == slot + TB
    assert (session.plan.start, session.plan.end) == (t, t + slot + TB)


class ClientClock:
    """What LeRobot's RobotClient does with replies, on a simulated clock: it executes one action per
    tick, stamps each observation with its last executed timestep t, sends one every tick while its
    queue is at most a chunk, and keeps a reply's actions for timesteps > t. A reply arrives `latency`
    ticks after its observation."""

    def __init__(self, session, obs, latency: int):
        self.session, self.obs, self.latency = session, obs, latency
        self.queue: dict[int, torch.Tensor] = {}
        self.in_flight: list[tuple[int, int, torch.Tensor]] = []  # arrival tick, t, actions
        self.executed, self.stalls = -1, 0

    def tick(self, now: int) -> None:
        for _, t, actions in [r for r in self.in_flight if r[0] <= now]:
            self.queue.update({t + i: a for i, a in enumerate(actions[0]) if t + i > self.executed})
        self.in_flight = [r for r in self.in_flight if r[0] > now]
        if self.executed + 1 in self.queue:
            self.executed += 1
            del self.queue[self.executed]
        else:
            self.stalls += 1
        if len(self.queue) <= TB:
            t = max(self.executed, 0)
            self.in_flight.append((now + self.latency, t, self.session.sdp_reply(self.obs, t)))


@pytest.mark.parametrize("max_delay", [0, 2])
def test_a_chunk_starts_delay_ticks_after_its_observation_on_a_client_clock(server_mod, max_delay):
    """The server streams when `delay_ticks` unexecuted actions are left, so the chunk built from the
    observation stamped t runs from t + 1 + delay_ticks, and the robot never waits for it; a policy
    trained with max_delay denoises it with that rest committed, one trained without as if it ran at
    t + 1."""
    delay = 2
    served, reference = twin_policies(max_delay=max_delay)
    session = session_with(server_mod, served, delay_ticks=delay)
    obs = history(served.config, batch_size=1)
    streams, original = [], served.predict_action_chunk

    def recorded(history_, committed=0, **kwargs):
        first_action = session.plan.end if session.plan is not None else session.current_t + 1
        streams.append((session.current_t, first_action, committed))
        return original(history_, committed=committed, **kwargs)

    served.predict_action_chunk = recorded
    real_reply = session.sdp_reply

    def reply(history_, t):
        session.current_t = t
        return real_reply(history_, t)

    session.sdp_reply = reply
    clock = ClientClock(session, obs, latency=delay)
    torch.manual_seed(0)
    for now in range(60):
        clock.tick(now)
    assert len(streams) >= 8
    gaps = [first_action - t - 1 for t, first_action, _ in streams[1:]]
    assert gaps == [delay] * len(gaps)  # observation-to-first-action gap: the delay, every chunk
    assert [c for *_, c in streams[1:]] == [delay if max_delay else 0] * len(gaps)
    assert clock.stalls == delay  # only while the episode's first chunk was on its way
    # the streamed chunks are the reference stream's, with the same committed actions
    torch.manual_seed(0)
    expected = [reference.predict_action_chunk(obs, committed=c) for *_, c in streams]
    torch.testing.assert_close(session.plan.actions[0, -TB:], expected[-1][0])


def test_history_is_the_clients_frames_by_timestep(server_mod, tmp_path):
    """Frame t - k is the observation sent at that timestep; one never sent repeats the next newer."""
    from lerobot.async_inference.helpers import TimedObservation

    served, _ = twin_policies(n_obs_steps=3)
    session = session_with(server_mod, served, tmp_path)

    def sent(t: int, agent_x: float):
        obs = TimedObservation(timestamp=time.time(), timestep=t, observation=raw_observation(agent_x))
        session.frames[t] = obs
        return session._process(obs)

    old, current = sent(7, 150.0), sent(9, 300.0)  # nothing was sent at timestep 8
    stacked = session._history(current, 9)["observation.state"]
    assert stacked.shape == (1, 3, 2)
    assert torch.equal(stacked[:, 0], old["observation.state"])
    assert torch.equal(stacked[:, 1], current["observation.state"]) and torch.equal(
        stacked[:, 2], stacked[:, 1]
    )
    assert not torch.equal(stacked[:, 0], stacked[:, 2])
    middle = sent(8, 220.0)
    assert torch.equal(session._history(current, 9)["observation.state"][:, 1], middle["observation.state"])
    del session.frames[7]  # now 7 was never sent: it repeats 8, the next newer frame, not the current one
    stacked = session._history(current, 9)["observation.state"]
    assert torch.equal(stacked[:, 0], middle["observation.state"]) and torch.equal(
        stacked[:, 1], stacked[:, 0]
    )


def test_raw_observation_and_feature_problems_are_named(server_mod, tmp_path):
    import numpy as np
    from lerobot.configs.policies import PreTrainedConfig

    features = pusht_features(tmp_path)
    assert server_mod.raw_observation_problem(raw_observation(), features) is None
    missing = raw_observation()
    del missing["block_kp3_x.pos"]
    assert "missing `block_kp3_x.pos`" in server_mod.raw_observation_problem(missing, features)
    shaped = {**raw_observation(), "agent_y.pos": np.zeros(3)}
    assert "`agent_y.pos` has shape (3,)" in server_mod.raw_observation_problem(shaped, features)
    camera = {**features, "observation.images.top": {"dtype": "image", "shape": (96, 96, 3), "names": None}}
    wrong = {**raw_observation(), "top": np.zeros((64, 64, 3))}
    assert "of shape (64, 64, 3)" in server_mod.raw_observation_problem(wrong, camera)

    config = PreTrainedConfig.from_pretrained(save_tiny_policy(tmp_path / "sdp"))
    assert server_mod.feature_problem(config, features) is None
    fewer = {"observation.state": {**features["observation.state"], "shape": (17,)}}
    assert "sends `observation.state` with 17 values and the policy takes 18" in server_mod.feature_problem(
        config, fewer
    )


# ---- over real gRPC on loopback ----------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(server_mod):
    config = server_mod.SDPPolicyServerConfig(
        host="127.0.0.1", port=free_port(), fps=10, obs_queue_timeout=0.3, session_timeout_s=2.0
    )
    grpc_server, service, port = server_mod.start_server(config)
    yield service, f"127.0.0.1:{port}"
    grpc_server.stop(grace=None)
    service.close()


def robot_client(tmp_path, address: str, policy_dir, name: str):
    from lerobot.async_inference.configs import RobotClientConfig
    from lerobot.async_inference.robot_client import RobotClient

    from lerobot_sdp.robots import PushTSimConfig

    robot = PushTSimConfig(calibration_dir=tmp_path / f"calibration_{name}", seed=len(name))
    config = RobotClientConfig(
        policy_type="sdp",
        pretrained_name_or_path=str(policy_dir),
        robot=robot,
        actions_per_chunk=3 * TB,
        server_address=address,
        fps=10,
    )
    return RobotClient(config)


class Running:
    """A RobotClient's two threads (action receiver, control loop), as `async_client` runs them."""

    def __init__(self, client):
        assert client.start(), "the client could not set up its policy on the server"
        self.client = client
        self.threads = [
            threading.Thread(target=client.receive_actions, daemon=True),
            threading.Thread(target=client.control_loop, kwargs={"task": ""}, daemon=True),
        ]
        for thread in self.threads:
            thread.start()

    def stop(self):
        self.client.shutdown_event.set()
        self.threads[1].join(timeout=10)
        self.client.stop()  # disconnects the robot, closes the channel
        self.threads[0].join(timeout=10)
        assert not any(t.is_alive() for t in self.threads)


def wait_for(condition, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def client_process(tmp_path, address: str, policy_dir, stats_path):
    """LeRobot's robot_client CLI with a simulated robot, as a user runs it (it loads the plugin itself).
    Each RobotClient in its own process: clients are told apart by their connection."""
    let_sigint_reach_children()  # stopped with SIGINT below, also when pytest runs in the background
    cmd = [
        sys.executable,
        "-m",
        "lerobot.async_inference.robot_client",
        "--robot.type=pusht_sim",
        f"--robot.calibration_dir={tmp_path / 'calibration_cli'}",
        f"--robot.stats_path={stats_path}",
        "--policy_type=sdp",
        f"--pretrained_name_or_path={policy_dir}",
        f"--actions_per_chunk={3 * TB}",
        f"--server_address={address}",
        "--fps=10",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    return subprocess.Popen(
        cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


@pytest.mark.slow
def test_robot_clients_drive_pusht_sim_through_the_server(server, tmp_path):
    """Two LeRobot RobotClients with simulated robots (one through LeRobot's CLI), each served by its own
    SDP session; one disconnecting mid-episode leaves the other served and its session is dropped after
    the timeout; the served plan stays within one reply of what the robot executed."""
    from lerobot_sdp import SDPPolicy

    service, address = server
    policy_dir = save_tiny_policy(tmp_path / "policy")
    stats_path = tmp_path / "cli_robot.json"
    cli = client_process(tmp_path, address, policy_dir, stats_path)
    a = Running(robot_client(tmp_path, address, policy_dir, "a"))
    try:

        def both_served():
            plans = [s.plan for s in list(service.sessions.values())]
            return len(plans) == 2 and all(p is not None and p.end >= 15 for p in plans)

        wait_for(both_served, timeout=60)
        policies = [s.policy for s in service.sessions.values()]
        assert all(isinstance(p, SDPPolicy) for p in policies) and policies[0] is not policies[1]
        a.stop()  # mid-episode
        wait_for(lambda: len(service.sessions) == 1, timeout=10)  # dropped after session_timeout_s
        (left,) = service.sessions.values()
        # the plans it serves, kept: once its client stops, its idle session is dropped and reset
        served, serve = [], left.sdp_reply

        def spy(*args, **kwargs):
            actions = serve(*args, **kwargs)
            served.append(left.plan)
            return actions

        left.sdp_reply = spy
        reached = left.plan.end
        wait_for(lambda: left.plan.end >= reached + 2 * TB)  # the other client is still served
    finally:
        if any(t.is_alive() for t in a.threads):
            a.stop()
        cli.send_signal(signal.SIGINT)
        log = cli.communicate(timeout=30)[0]
    stats = json.loads(stats_path.read_text())
    executed = stats["actions_sent"] - 1  # the timestep of its last action
    last = served[-1]
    assert last.start <= executed < last.end <= executed + 1 + 3 * TB, (
        last.start,
        executed,
        log,
    )
    assert "Failed to connect" not in log and stats["actions_sent"] >= 15


class StubClient:
    """A bare gRPC client speaking LeRobot's protocol, to send what LeRobot's RobotClient would not."""

    def __init__(self, address: str):
        import grpc
        from lerobot.transport import services_pb2, services_pb2_grpc

        self.pb2 = services_pb2
        # its own connection: channels of one process otherwise share one, hence one server session
        self.channel = grpc.insecure_channel(address, options=[("grpc.use_local_subchannel_pool", 1)])
        self.stub = services_pb2_grpc.AsyncInferenceStub(self.channel)
        self.stub.Ready(services_pb2.Empty())

    def setup(self, tmp_path, policy_dir, policy_type: str = "sdp"):
        from lerobot.async_inference.helpers import RemotePolicyConfig

        specs = RemotePolicyConfig(policy_type, str(policy_dir), pusht_features(tmp_path), 3 * TB)
        self.stub.SendPolicyInstructions(self.pb2.PolicySetup(data=pickle.dumps(specs)))

    def act(self, raw: dict, timestep: int, must_go: bool = True):
        """Send one observation and return the actions (TimedAction list)."""
        from lerobot.async_inference.helpers import TimedObservation
        from lerobot.transport.utils import send_bytes_in_chunks

        obs = TimedObservation(timestamp=time.time(), timestep=timestep, observation=raw, must_go=must_go)
        self.stub.SendObservations(send_bytes_in_chunks(pickle.dumps(obs), self.pb2.Observation, silent=True))
        reply = self.stub.GetActions(self.pb2.Empty())
        return pickle.loads(reply.data) if reply.data else []


def rpc_error(call):
    import grpc

    with pytest.raises(grpc.RpcError) as info:
        call()
    return info.value


def test_a_checkpoint_that_is_not_the_asked_policy_is_refused_on_the_client(server, tmp_path):
    import grpc
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    _, address = server
    dp_dir = tmp_path / "dp"
    cfg = tiny_config()
    DiffusionConfig(input_features=cfg.input_features, output_features=cfg.output_features).save_pretrained(
        dp_dir
    )
    client = StubClient(address)
    error = rpc_error(lambda: client.setup(tmp_path, dp_dir))
    assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "holds a `diffusion` policy" in error.details() and "--policy_type=diffusion" in error.details()
    error = rpc_error(lambda: client.setup(tmp_path, tmp_path / "nowhere"))
    assert "Cannot read a policy config" in error.details()
    # LeRobot's own RobotClient reports it and does not start
    records = []
    handler = logging.Handler(level=logging.ERROR)
    handler.emit = lambda record: records.append(record.getMessage())
    logging.getLogger("robot_client").addHandler(handler)
    try:
        assert not robot_client(tmp_path, address, dp_dir, "c").start()
    finally:
        logging.getLogger("robot_client").removeHandler(handler)
    assert any("Failed to connect" in r and "holds a `diffusion` policy" in r for r in records), records


def test_bad_observations_are_refused_on_the_client_and_the_server_goes_on(server, tmp_path):
    """A missing key, a mis-shaped value, NaN: each an INVALID_ARGUMENT naming it; the same client then
    gets actions for a good observation at the same timestep, and another client was served meanwhile."""
    import grpc
    import numpy as np

    service, address = server
    policy_dir = save_tiny_policy(tmp_path / "policy")
    faulty, healthy = StubClient(address), StubClient(address)
    faulty.setup(tmp_path, policy_dir)
    healthy.setup(tmp_path, policy_dir)
    missing = raw_observation()
    del missing["block_kp5_y.pos"]
    bad = {
        "missing `block_kp5_y.pos`": missing,
        "`agent_x.pos` has shape (2,)": {**raw_observation(), "agent_x.pos": np.array([1.0, 2.0])},
        "is nan (NaN or inf)": {**raw_observation(), "block_kp0_x.pos": float("nan")},
    }
    for t, (message, raw) in enumerate(bad.items()):
        error = rpc_error(lambda raw=raw, t=t: faulty.act(raw, t))
        assert error.code() == grpc.StatusCode.INVALID_ARGUMENT and message in error.details()
        served = healthy.act(raw_observation(100.0 + t), t)  # a chunk, or the rest while it lasts
        assert served and served[-1].get_timestep() > t
    # not must-go, so LeRobot's server would skip it if the refused timestep counted as predicted
    actions = faulty.act(raw_observation(), len(bad) - 1, must_go=False)
    assert len(actions) == TB and actions[0].get_timestep() == len(bad) - 1
    assert torch.isfinite(torch.stack([a.get_action() for a in actions])).all()
    assert len(service.sessions) == 2


def test_a_prediction_that_fails_leaves_its_timestep_free_for_a_retry(server, tmp_path):
    """A valid observation whose prediction fails (the model raises) is not counted as predicted: the
    same timestep sent again, not must-go, is served (LeRobot's server skips predicted timesteps)."""
    import contextlib

    import grpc

    service, address = server
    client = StubClient(address)
    client.setup(tmp_path, save_tiny_policy(tmp_path / "policy"))
    (session,) = service.sessions.values()
    predict, calls = session.policy.predict_action_chunk, []

    def fails_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("the model failed")
        return predict(*args, **kwargs)

    session.policy.predict_action_chunk = fails_once
    with contextlib.suppress(grpc.RpcError):  # refused with the error, or no actions: either way
        assert client.act(raw_observation(), 0) == []
    actions = client.act(raw_observation(50.0), 0, must_go=False)  # a new frame at that timestep
    assert len(calls) == 2 and len(actions) == TB and actions[0].get_timestep() == 0


def test_a_session_busy_in_a_long_call_is_not_dropped_as_idle(server_mod):
    """A chunk slower than --session_timeout_s (a loaded machine) keeps its session: only sessions
    with no call running are idle."""

    class Context:
        def __init__(self, peer):
            self._peer = peer

        def peer(self):
            return self._peer

        def invocation_metadata(self):
            return ()

    service = server_mod.SDPPolicyServer(server_mod.SDPPolicyServerConfig(session_timeout_s=0.05))
    slow, other = Context("ipv4:127.0.0.1:1"), Context("ipv4:127.0.0.1:2")
    seen = {}

    def long_call(request, context):
        time.sleep(0.2)  # meanwhile another client calls, which sweeps idle sessions
        service.call("Ready", None, other)
        seen["kept"] = slow.peer() in service.sessions
        return "done"

    session = service.session(slow, "Ready")
    session.in_flight -= 1  # session() counted a call; this test drives one by hand below
    session.Ready = long_call
    service.sessions[other.peer()] = server_mod.ClientPolicyServer(service.config)
    service.sessions[other.peer()].Ready = lambda request, context: None
    assert service.call("Ready", None, slow) == "done" and seen["kept"]
    time.sleep(0.1)  # now idle for longer than the timeout: the next call from another client drops it
    service.call("Ready", None, other)
    assert slow.peer() not in service.sessions and session.in_flight == 0


def test_the_server_listens_on_localhost_unless_told_otherwise(server_mod):
    assert server_mod.SDPPolicyServerConfig().host in server_mod.LOOPBACK
    with pytest.raises(ValueError, match="max_calls_per_client must be at least 1"):
        server_mod.SDPPolicyServerConfig(max_calls_per_client=0)
    with pytest.raises(ValueError, match="receive_timeout_s must be positive"):
        server_mod.SDPPolicyServerConfig(receive_timeout_s=0)


class FakeClock:
    """A clock a test moves by hand (seconds), for the session's timing."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def served_session(server_mod, tmp_path, clock=None, **config):
    """A session with the tiny policy and pusht_sim's features, served through LeRobot's own path
    (`_enqueue_observation`, then `_predict_action_chunk` on the queued observation)."""
    served, reference = twin_policies()
    session = session_with(server_mod, served, tmp_path, **config)
    if clock is not None:
        session.clock = clock
    return session, reference


def serve(session, t: int, agent_x: float = 100.0, must_go: bool = True):
    """The client's observation stamped t goes in; the actions of the one the server runs come out
    (None when LeRobot's filters skip it)."""
    from lerobot.async_inference.helpers import TimedObservation

    obs = TimedObservation(timestamp=time.time(), timestep=t, observation=raw_observation(agent_x))
    obs.must_go = must_go
    if not session._enqueue_observation(obs):
        return None
    return session._predict_action_chunk(session.observation_queue.get_nowait())


class Peer:
    def peer(self):
        return "ipv4:127.0.0.1:1"


def reply_of(session, t: int, agent_x: float = 100.0) -> list:
    """LeRobot's whole GetActions for the client's observation stamped t, unpickled."""
    from lerobot.async_inference.helpers import TimedObservation

    session._enqueue_observation(TimedObservation(time.time(), t, raw_observation(agent_x), must_go=True))
    return pickle.loads(session.GetActions(None, Peer()).data)


def test_a_restart_without_ready_at_the_plans_own_start_restarts_the_stream(server_mod, tmp_path):
    """The client started over at timestep 0 while the plan also starts at 0: the newer timesteps it
    had sent before show the restart, and the reply is a new stream, not the old episode's plan."""
    session, _ = served_session(server_mod, tmp_path, delay_ticks=0)
    torch.manual_seed(1)
    old = serve(session, 0)
    serve(session, 1, agent_x=120.0, must_go=False)  # the plan still has more than 0 left: no stream
    torch.manual_seed(2)
    new = serve(session, 0, agent_x=100.0)  # the client restarted
    assert [a.get_timestep() for a in new] == list(range(TB))
    assert not torch.equal(*(torch.stack([a.get_action() for a in reply]) for reply in (new, old)))
    assert session.plan.start == 0 and session.plan.episode == session.episode == 1


def test_an_observation_of_a_left_episode_is_never_run(server_mod, tmp_path):
    """One queued before the client started over (LeRobot's queue holds one) is dropped when its turn
    comes: its reply would bring the old episode's plan back."""
    session, _ = served_session(server_mod, tmp_path, delay_ticks=0)
    from lerobot.async_inference.helpers import TimedObservation

    serve(session, 0)
    session._enqueue_observation(TimedObservation(time.time(), 3, raw_observation(130.0), must_go=True))
    stale = session.observation_queue.get_nowait()
    session._enqueue_observation(TimedObservation(time.time(), 0, raw_observation(100.0), must_go=True))
    with pytest.raises(server_mod.StaleObservationError):
        session._predict_action_chunk(stale)
    assert 3 not in session._predicted_timesteps and session.error is None


def test_after_a_failed_prediction_the_same_state_is_retried(server_mod, tmp_path):
    """A transient failure (here the model raising, as on an out-of-memory): the client, whose queue is
    empty, sends the same state again, not must-go (RobotClient cleared its must-go flag). It is run,
    not dropped as "too similar" to the observation that failed."""
    session, _ = served_session(server_mod, tmp_path)
    predict, calls = session.policy.predict_action_chunk, []

    def fails_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("CUDA out of memory")
        return predict(*args, **kwargs)

    session.policy.predict_action_chunk = fails_once
    with pytest.raises(RuntimeError, match="out of memory"):
        serve(session, 0)
    actions = serve(session, 0, must_go=False)  # the same state, at the same timestep
    assert actions is not None and len(actions) == TB and len(calls) == 2


def test_the_delay_leaves_out_a_streams_first_chunk_counts_the_whole_reply_and_is_capped(
    server_mod, tmp_path
):
    """The delay in ticks is the slowest recent reply from the observation's arrival (pre- and
    post-processing included) to its end, at --fps; a stream's first chunk (priming, warm-up) does not
    count, and the delay never reaches a whole chunk."""
    clock = FakeClock()
    session, _ = served_session(server_mod, tmp_path, clock=clock, fps=30, inference_latency=0.0)
    predict, preprocess = session.policy.predict_action_chunk, session.preprocessor
    chunk_s = [3.0]  # the first chunk: 3 s, 90 ticks at 30 fps

    def timed_predict(*args, **kwargs):
        clock.now += chunk_s[0]
        return predict(*args, **kwargs)

    def slow_preprocess(obs):
        clock.now += 0.05  # 1.5 ticks of preprocessing, which the estimate must see
        return preprocess(obs)

    session.policy.predict_action_chunk, session.preprocessor = timed_predict, slow_preprocess
    t = 0
    for _ in range(3):
        assert reply_of(session, t)[0].get_timestep() == t
        chunk_s[0] = 0.01
        t = session.plan.end - 1  # the client ran all but the last sent action
    # 0.05 s of preprocessing (the history's other frame was never sent), 0.01 s of denoising: 1.8 ticks
    assert session.delay_ticks() == math.ceil((0.05 + 0.01) * 30) == 2
    session.latencies.append(3.0)  # a later slow reply: capped at a chunk less one
    assert session.delay_ticks() == TB - 1


def test_a_vanished_clients_session_is_dropped_without_any_other_call(server_mod):
    """The last client vanished: no call will ever come to sweep its session, so the server's own
    sweeper drops it (and frees its policy) within the timeout and a quarter."""
    import weakref

    config = server_mod.SDPPolicyServerConfig(host="127.0.0.1", port=free_port(), session_timeout_s=0.2)
    grpc_server, service, _ = server_mod.start_server(config)
    session = service.sessions["ipv4:127.0.0.1:1"] = server_mod.ClientPolicyServer(service.config)
    session.policy = torch.nn.Linear(1, 1)
    session.policy.reset = lambda: None
    policy = weakref.ref(session.policy)
    del session
    try:
        wait_for(lambda: not service.sessions, timeout=0.2 * 1.25 + 0.2)
        assert policy() is None  # nothing else held it
    finally:
        grpc_server.stop(grace=None)
        service.close()
    sweeper = [t for t in threading.enumerate() if t.name == "sdp-session-sweeper"]
    for thread in sweeper:
        thread.join(timeout=1)
    assert not any(t.is_alive() for t in sweeper)
