"""Random deployment schedules on a virtual clock (`benchmarks/deployment_schedules.py`): the policy
server under LeRobot's RobotClient semantics and the RTC adapter under LeRobot's RTC engine and
ActionQueue, with random inference times, jitter, restarts, reconnects, failures and vanished
clients; the upstream ActionQueue patch applied to LeRobot 0.6.1's file. A failing schedule is
reported with its seed and a shrunk schedule."""

import random
import sys
from pathlib import Path

import pytest
import torch
from lerobot.policies.rtc import ActionQueue
from lerobot.policies.rtc.configuration_rtc import RTCConfig

from lerobot_sdp.benchmarks import deployment_schedules as ds

REPO = Path(__file__).resolve().parents[1]
PATCH = REPO / "docs" / "upstream" / "lerobot-0.6.1-rtc-actions-run.patch"
SCHEDULES = 150  # per engine and variant: hundreds in all, in well under a minute
TICKS = 240


@pytest.fixture(scope="module")
def patched_queue(tmp_path_factory):
    """LeRobot 0.6.1's ActionQueue with the upstream patch applied, imported from a patched copy."""
    yield ds.patched_action_queue(PATCH, tmp_path_factory.mktemp("lerobot"))
    del sys.modules["lerobot.policies.rtc._action_queue_patched"]


def left_after(queue_class, popped_during_call: int, real_delay: int) -> list[float]:
    """A queue of actions 0..9 (by value); the frame's tick ran action 2 and the thread called with
    index 3; `popped_during_call` more ran before the result (the frame's tick 0, then 1, 2, ...:
    the values 100 + i) came back, and the engine estimated `real_delay`. What the robot runs next."""
    queue = queue_class(RTCConfig(execution_horizon=10))
    first = torch.arange(10.0).unsqueeze(1)
    queue.merge(first, first, real_delay=0)
    for _ in range(3):
        queue.get()
    index_before = queue.get_action_index()
    for _ in range(popped_during_call):
        queue.get()
    result = 100 + torch.arange(12.0).unsqueeze(1)
    queue.merge(result, result, real_delay, action_index_before_inference=index_before)
    return [float(queue.get()) for _ in range(2)]


def test_the_upstream_patch_drops_the_actions_that_ran_since_the_frame(patched_queue):
    """The frame's tick (result slot 0) and the 2 actions that ran during the call: slots 0-2 dropped,
    slot 3 runs next, whatever the latency estimate. LeRobot's own queue drops the estimate: with an
    estimate of 2 (a 1.5-tick call that began part-way into a tick) the robot runs slot 2, the result's
    copy of an action it already ran, and every later action a tick late."""
    assert left_after(patched_queue, 2, real_delay=2) == [103.0, 104.0]
    assert left_after(patched_queue, 2, real_delay=3) == [103.0, 104.0]
    assert left_after(ActionQueue, 2, real_delay=2) == [102.0, 103.0]
    # the first call of an episode, slower than a tick: nothing ran, only the frame's slot goes
    queue = patched_queue(RTCConfig(execution_horizon=10))
    result = 100 + torch.arange(6.0).unsqueeze(1)
    queue.merge(result, result, real_delay=3, action_index_before_inference=0)
    assert float(queue.get()) == 101.0


def run_or_report(engine: str, seed: int, variant: dict) -> dict:
    """Run seed's schedule; on a violation fail with the seed and a shrunk schedule."""
    steps = ds.random_schedule(random.Random(seed), engine, TICKS)
    try:
        return ds.run_schedule(engine, steps, variant)
    except ds.InvariantError as e:

        def fails(candidate):
            try:
                ds.run_schedule(engine, candidate, variant)
            except ds.InvariantError:
                return True
            return False

        shrunk = ds.shrink(steps, fails)
        pytest.fail(
            f"{engine} seed {seed} { ({k: v for k, v in variant.items() if k != 'policy'}) }: {e}\n"
            f"shrunk schedule ({len(shrunk)} ticks, plain ones omitted): {ds.schedule_summary(shrunk)}"
        )


@pytest.mark.parametrize("max_delay", [0, 3])
def test_random_schedules_on_the_policy_server(max_delay):
    executed = streams = 0
    for seed in range(SCHEDULES):
        counts = run_or_report("async", seed, {"max_delay": max_delay})
        executed, streams = executed + counts["executed"], streams + counts["streams"]
    assert executed > SCHEDULES * TICKS / 2 and streams > SCHEDULES * 10  # the robots did run


@pytest.mark.parametrize(("k", "max_delay"), [(0, 0), (1, 3), (2, 3)])
def test_random_schedules_under_the_rtc_engine_with_the_upstream_patch(patched_queue, k, max_delay):
    policy = ds.small_sdp(max_delay)
    executed = 0
    for seed in range(SCHEDULES):
        counts = run_or_report("rtc", seed, {"k": k, "policy": policy, "queue_class": patched_queue})
        assert counts["repeated"] == counts["skipped"] == 0
        executed += counts["executed"]
    assert executed > SCHEDULES * TICKS / 2


def test_lerobots_own_queue_repeats_or_loses_actions_only_where_its_delay_model_says(patched_queue):
    """Without the patch every deviation is the estimate's: a repeat where the call crossed one more
    tick than ceil(latency / dt) counts, a loss where fewer ran (the queue ran dry); some schedules show
    each."""
    policy = ds.small_sdp(0)
    totals = {"repeated": 0, "skipped": 0}
    for seed in range(SCHEDULES):
        counts = run_or_report("rtc", seed, {"k": 1, "policy": policy, "queue_class": ActionQueue})
        totals = {key: totals[key] + counts[key] for key in totals}
    assert totals["repeated"] > 0 and totals["skipped"] > 0


def test_a_server_bug_is_found_and_shrunk(monkeypatch):
    """The driver finds a broken server: one that lets LeRobot's "too similar" filter drop the retry
    after the episode's first prediction failed stalls the robot (which holds still, so its state is
    the same) for good; the schedule shrinks to the failure and the ticks it takes to see the stall."""
    from lerobot_sdp import policy_server

    original = policy_server.ClientPolicyServer._enqueue_observation

    def forgets_the_failure(self, obs):
        self.retry = False
        return original(self, obs)

    monkeypatch.setattr(policy_server.ClientPolicyServer, "_enqueue_observation", forgets_the_failure)
    steps = [ds.Step(fail=True)] + [ds.Step()] * 40

    def fails(candidate):
        try:
            ds.run_schedule("async", candidate, {"max_delay": 0})
        except ds.InvariantError as e:
            return "waited" in str(e)
        return False

    assert fails(steps)
    shrunk = ds.shrink(steps, fails)
    assert fails(shrunk) and len(shrunk) < len(steps) and any(s.fail for s in shrunk)
    monkeypatch.setattr(policy_server.ClientPolicyServer, "_enqueue_observation", original)
    assert not fails(steps)


def test_the_action_log_refuses_another_episodes_actions_repeats_and_skips():
    """The checker itself: actions in order pass; a repeat, a skip or an action of a stream started
    before the current episode fails; the lenient log (LeRobot's own queue) counts repeats and skips."""

    def act(log, stream, pos, tick=0):
        log.run(torch.tensor([float(stream), float(pos)]), tick)

    log = ds.ActionLog()
    log.stream_started[7] = 1.0
    log.new_episode(0.5)
    act(log, 7, 0)
    act(log, 7, 1)
    with pytest.raises(ds.InvariantError, match="ran its action 1, expected 2"):
        act(log, 7, 1)
    with pytest.raises(ds.InvariantError, match="ran its action 3, expected 2"):
        act(log, 7, 3)
    log.new_episode(2.0)  # stream 7 began before this episode
    with pytest.raises(ds.InvariantError, match="not of this episode"):
        act(log, 7, 2)
    log.stream_started[8] = 2.0
    act(log, 8, 0)
    assert log.executed == 3

    lenient = ds.ActionLog(lenient=True)
    lenient.stream_started[1] = 0.0
    for pos in (0, 1, 1, 4, 5):
        act(lenient, 1, pos)
    assert (lenient.repeated, lenient.skipped, lenient.executed) == (1, 2, 5)
