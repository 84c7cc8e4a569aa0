"""The policy server under faults, over real gRPC on loopback: while a well-behaved LeRobot RobotClient
drives `pusht_sim` in real time, other clients send bad frames, restart without Ready, reconnect, stall
uploads, upload too much, send code, and disappear. Each bad client gets an error that names the
problem, the good client keeps receiving actions, and nothing is left behind."""

import gc
import json
import pickle
import threading
import time
import weakref

import grpc
import numpy as np
import pytest
import torch
from lerobot.async_inference.helpers import TimedObservation
from lerobot.transport import services_pb2
from lerobot.transport.utils import send_bytes_in_chunks
from sdp_test_utils import save_tiny_policy
from test_policy_server import TB, Running, StubClient, free_port, raw_observation, robot_client, wait_for
from test_protocol_pickle import WritesMarker

RECEIVE_TIMEOUT_S = 1.0
SESSION_TIMEOUT_S = 2.0
CALLS_PER_CLIENT = 3


class Client(StubClient):
    """A client speaking LeRobot's protocol; with `client_id`, it names itself in gRPC metadata."""

    def __init__(self, address: str, client_id: str | None = None, key: str = "x-sdp-client-id"):
        self.address, self.client_id, self.key = address, client_id, key
        self.connect()
        self.stub.Ready(services_pb2.Empty(), metadata=self.metadata)

    @property
    def metadata(self):
        return ((self.key, self.client_id),) if self.client_id else ()

    def connect(self):
        """A new connection, from a new port (as after a network drop)."""
        from lerobot.transport import services_pb2_grpc

        self.channel = grpc.insecure_channel(self.address, options=[("grpc.use_local_subchannel_pool", 1)])
        self.stub = services_pb2_grpc.AsyncInferenceStub(self.channel)
        self.pb2 = services_pb2

    def setup(self, tmp_path, policy_dir):
        from lerobot.async_inference.helpers import RemotePolicyConfig
        from test_policy_server import pusht_features

        specs = RemotePolicyConfig("sdp", str(policy_dir), pusht_features(tmp_path), 3 * TB)
        setup = services_pb2.PolicySetup(data=pickle.dumps(specs))
        self.stub.SendPolicyInstructions(setup, metadata=self.metadata)

    def upload(self, data: bytes):
        chunks = send_bytes_in_chunks(data, services_pb2.Observation)
        self.stub.SendObservations(chunks, metadata=self.metadata)

    def act(self, raw: dict, timestep: int, must_go: bool = True):
        obs = TimedObservation(timestamp=time.time(), timestep=timestep, observation=raw, must_go=must_go)
        self.upload(pickle.dumps(obs))
        reply = self.stub.GetActions(services_pb2.Empty(), metadata=self.metadata)
        return pickle.loads(reply.data) if reply.data else []  # nosec: from our own server

    def close(self):
        self.channel.close()


def refused(call) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as info:
        call()
    return info.value


@pytest.fixture
def served(server_mod, tmp_path):
    """A server with short limits, and a LeRobot RobotClient driving pusht_sim through it."""
    config = server_mod.SDPPolicyServerConfig(
        host="127.0.0.1",
        port=free_port(),
        fps=10,
        obs_queue_timeout=0.3,
        session_timeout_s=SESSION_TIMEOUT_S,
        receive_timeout_s=RECEIVE_TIMEOUT_S,
        max_observation_mb=1.0,
        max_calls_per_client=CALLS_PER_CLIENT,
        max_clients=8,  # the bad clients of consecutive faults, until their sessions are dropped
    )
    grpc_server, service, port = server_mod.start_server(config)
    policy_dir = save_tiny_policy(tmp_path / "policy")
    good = robot_client(tmp_path, f"127.0.0.1:{port}", policy_dir, "good")
    good.robot.config.stats_path = tmp_path / "good.json"
    good.robot.config.episode_length = 100_000  # the run outlasts every fault
    running = Running(good)
    wait_for(lambda: good.robot.actions_sent > 5, timeout=60)
    try:
        yield service, f"127.0.0.1:{port}", policy_dir, good.robot
    finally:
        running.stop()
        grpc_server.stop(grace=None)
        service.close()


def keeps_acting(robot, fault):
    """Run `fault`, then check the good client's robot acted during it (when it outlasts a few
    ticks) and after it. A fault shorter than that can fall between two actions however well the
    server serves; the run's longest gap between actions, checked at the end, covers those."""
    before, start = robot.actions_sent, time.monotonic()
    result = fault()
    reached, lasted_s = robot.actions_sent, time.monotonic() - start
    if lasted_s > 3 / robot.config.fps:
        assert reached > before, f"the good client got no action during a {lasted_s:.2f} s fault"
    wait_for(lambda: robot.actions_sent >= reached + 3, timeout=10)
    return result


def stalled_uploads(client, n: int, release: threading.Event):
    """n SendObservations calls that send a first chunk and then nothing (until `release`)."""

    def requests():
        yield services_pb2.Observation(transfer_state=services_pb2.TransferState.TRANSFER_BEGIN, data=b"\x80")
        release.wait(30)

    return [client.stub.SendObservations.future(requests(), metadata=client.metadata) for _ in range(n)]


def thread_counts() -> tuple[int, int]:
    """(the gRPC server's worker threads, every other thread of this process)."""
    names = [t.name for t in threading.enumerate()]
    pool = sum(name.startswith("ThreadPoolExecutor") for name in names)
    return pool, len(names) - pool


@pytest.mark.slow
def test_faults_leave_the_good_client_served_and_nothing_behind(served, server_mod, tmp_path):
    service, address, policy_dir, robot = served

    def bad_frames():
        bad = Client(address, "frames")
        bad.setup(tmp_path, policy_dir)
        missing = raw_observation()
        del missing["block_kp3_x.pos"]
        faults = {
            "`block_kp0_x.pos` is nan (NaN or inf)": {**raw_observation(), "block_kp0_x.pos": float("nan")},
            "`agent_y.pos` is inf (NaN or inf)": {**raw_observation(), "agent_y.pos": np.inf},
            "missing `block_kp3_x.pos`": missing,
            "`agent_x.pos` has shape (3,)": {**raw_observation(), "agent_x.pos": np.zeros(3)},
            "`agent_x.pos` is a str; expected a number": {**raw_observation(), "agent_x.pos": "left"},
        }
        for t, (message, raw) in enumerate(faults.items()):
            error = refused(lambda raw=raw, t=t: bad.act(raw, t))
            assert error.code() == grpc.StatusCode.INVALID_ARGUMENT and message in error.details()
        session = service.sessions["id:frames"]
        assert not session.frames, "a refused frame was kept"
        # the next valid frames are served at once: no refused frame sits in their history
        for t in range(len(faults), len(faults) + 3):
            actions = bad.act(raw_observation(100.0 + t), t)
            assert actions and torch.isfinite(torch.stack([a.get_action() for a in actions])).all()
        assert sorted(session.frames) == list(range(len(faults), len(faults) + 3))
        bad.close()

    def restart_without_ready():
        client = Client(address, "restart")
        client.setup(tmp_path, policy_dir)
        for t in range(6):
            client.act(raw_observation(100.0 + t), t)
        session = service.sessions["id:restart"]
        old_plan = session.plan
        # not must-go, at a timestep already predicted, the same as the last frame run: LeRobot's
        # bookkeeping from the old episode would skip it
        actions = client.act(raw_observation(105.0), 0, must_go=False)
        assert actions and actions[0].get_timestep() == 0
        assert list(session.frames) == [0] and session.plan.start == 0 and session.plan is not old_plan
        assert session._predicted_timesteps == {0}  # the old episode's are gone
        client.close()

    def reconnect():
        named = Client(address, "robot-7", key="x-lerobot-client-id")  # as docs/upstream's client
        named.setup(tmp_path, policy_dir)
        named.act(raw_observation(), 0)
        session = service.sessions["id:robot-7"]
        named.close()
        named.connect()  # a new connection, a new port: the same session
        actions = named.act(raw_observation(105.0), 1)
        assert actions and actions[0].get_timestep() == 1
        assert service.sessions["id:robot-7"] is session and sorted(session.frames) == [0, 1]
        named.close()
        anonymous = Client(address)
        anonymous.setup(tmp_path, policy_dir)
        anonymous.act(raw_observation(), 0)
        anonymous.close()
        anonymous.connect()
        error = refused(lambda: anonymous.act(raw_observation(), 1))
        assert error.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "Send Ready and the policy instructions again" in error.details()

    def stalls():
        staller = Client(address, "staller")
        staller.setup(tmp_path, policy_dir)
        release = threading.Event()
        calls = stalled_uploads(staller, 8, release)
        try:
            start = time.monotonic()
            Client(address, "newcomer").close()  # Ready answers while the uploads stall
            ready_s = time.monotonic() - start
            codes = [call.exception().code() for call in calls]  # each ends: cancelled or refused
            ended_s = time.monotonic() - start
        finally:
            release.set()
        assert ready_s < 1.0, ready_s
        assert codes.count(grpc.StatusCode.CANCELLED) == CALLS_PER_CLIENT  # stalled, cut off
        limited = [c for c in calls if c.exception().code() == grpc.StatusCode.RESOURCE_EXHAUSTED]
        assert len(limited) == 8 - CALLS_PER_CLIENT
        assert "--max_calls_per_client" in limited[0].exception().details()
        assert ended_s < RECEIVE_TIMEOUT_S + 2.0, ended_s
        staller.act(raw_observation(), 0)  # its own session still works
        staller.close()

    def oversized():
        big = Client(address, "big")
        big.setup(tmp_path, policy_dir)
        raw = {**raw_observation(), "extra": np.zeros(2**20 // 8 + 1)}  # over 1 MiB
        obs = TimedObservation(timestamp=time.time(), timestep=0, observation=raw)
        error = refused(lambda: big.upload(pickle.dumps(obs)))
        assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "--max_observation_mb" in error.details()
        big.close()

    def code_payloads():
        attacker = Client(address, "attacker")
        marker = tmp_path / "ran"
        payload = pickle.dumps(WritesMarker(marker))
        error = refused(lambda: attacker.stub.SendPolicyInstructions(services_pb2.PolicySetup(data=payload)))
        assert error.code() == grpc.StatusCode.INVALID_ARGUMENT and "builtins.exec" in error.details()
        attacker.setup(tmp_path, policy_dir)
        obs = TimedObservation(timestamp=0.0, timestep=0, observation={"x": WritesMarker(marker)})
        error = refused(lambda: attacker.upload(pickle.dumps(obs)))
        assert error.code() == grpc.StatusCode.INVALID_ARGUMENT and "builtins.exec" in error.details()
        assert not marker.exists()
        attacker.close()

    def vanishes_mid_upload():
        """A client that stalls an upload and is never heard from again: its call is cut off, then
        its session is dropped and its policy freed; its next call is told to set up again."""
        gone = Client(address, "gone")
        gone.setup(tmp_path, policy_dir)
        policy = weakref.ref(service.sessions["id:gone"].policy)
        release = threading.Event()
        (call,) = stalled_uploads(gone, 1, release)
        assert call.exception().code() == grpc.StatusCode.CANCELLED
        release.set()
        wait_for(lambda: "id:gone" not in service.sessions, timeout=SESSION_TIMEOUT_S + 5)
        gc.collect()
        assert policy() is None, "the dropped session's policy is still held"
        error = refused(lambda: gone.act(raw_observation(), 5))
        assert error.code() == grpc.StatusCode.FAILED_PRECONDITION
        gone.close()

    others_before = thread_counts()[1]
    for fault in [bad_frames, restart_without_ready, reconnect, stalls, oversized, code_payloads]:
        keeps_acting(robot, fault)
    keeps_acting(robot, vanishes_mid_upload)
    # every bad client's session is dropped once idle; the good client's stays
    wait_for(lambda: len(service.sessions) == 1, timeout=SESSION_TIMEOUT_S + 5)
    # no thread outlives its fault; the server's pool stays within its size
    wait_for(lambda: thread_counts()[1] <= others_before, timeout=10)
    assert thread_counts()[0] <= server_mod.worker_threads(service.config)
    time.sleep(0.5)
    stats = robot.stats()
    print(json.dumps({"longest_gap_s": stats["longest_gap_s"], "missed_ticks": stats["missed_ticks"]}))
    assert stats["longest_gap_s"] < 1.0, stats
