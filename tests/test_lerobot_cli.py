"""Running LeRobot's commands as subprocesses (`lerobot_sdp.lerobot_cli`)."""

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

# A parent started as a shell's `cmd &` starts: SIGINT ignored. It starts a Python child, waits until
# the child runs, sends it SIGINT (as our deployment bench and tests stop LeRobot's robot client) and
# prints the child's exit code, or "ignored" when the child kept running.
PARENT = """
import signal, subprocess, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
from lerobot_sdp.lerobot_cli import let_sigint_reach_children
if sys.argv[1] == "fix":
    let_sigint_reach_children()
child = subprocess.Popen(
    [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(30)"], stdout=subprocess.PIPE
)
child.stdout.readline()
child.send_signal(signal.SIGINT)
try:
    print(child.wait(timeout=3))
except subprocess.TimeoutExpired:
    child.kill()
    print("ignored")
"""


def parent(mode: str) -> str:
    done = subprocess.run([sys.executable, "-c", PARENT, mode], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()[-1]


def test_children_of_a_background_process_stop_on_sigint():
    assert parent("as_is") == "ignored"  # the trap: the child inherits SIGINT ignored
    assert parent("fix") == "-2"  # KeyboardInterrupt ends the child (Python exits by SIGINT)


def test_evaluate_all_runs_jobs_at_once_and_skips_finished_ones(tmp_path, monkeypatch):
    from lerobot_sdp import lerobot_cli

    lock, active, peak, started = threading.Lock(), [0], [0], []

    def fake_run_logged(cmd, log, echo=True):
        eval_dir = Path(next(a for a in cmd if a.startswith("--output_dir=")).split("=", 1)[1])
        with lock:
            active[0] += 1
            peak[0] = max(peak[0], active[0])
            started.append(eval_dir.name)
        time.sleep(0.1)
        eval_dir.mkdir(parents=True)
        (eval_dir / "eval_info.json").write_text(json.dumps({"overall": {}}))
        with lock:
            active[0] -= 1

    monkeypatch.setattr(lerobot_cli, "run_logged", fake_run_logged)
    done = tmp_path / "done"
    done.mkdir()
    (done / "eval_info.json").write_text(json.dumps({"overall": {}}))
    evaluations = [
        lerobot_cli.Evaluation(tmp_path / "model", tmp_path / name, [], tmp_path / f"{name}.log")
        for name in ("a", "b", "c", "d", "done")
    ]
    lerobot_cli.evaluate_all(evaluations, jobs=2)
    assert sorted(started) == ["a", "b", "c", "d"]  # a finished evaluation is not run again
    assert peak[0] == 2  # two at once, never more
    peak[0] = 0
    lerobot_cli.evaluate_all(
        [lerobot_cli.Evaluation(tmp_path / "m", tmp_path / n, [], tmp_path / "l") for n in "xy"]
    )
    assert peak[0] == 1  # one at a time by default


def test_a_command_left_by_an_error_is_stopped_not_waited_for(tmp_path):
    """An exception while the output is read (a test's time limit, a failing caller) ends the child:
    without that, Popen's exit would wait for it (here 60 s) and a hung child would hold the caller."""
    import os
    import signal

    from lerobot_sdp.lerobot_cli import run_logged

    def limit(*_):
        raise TimeoutError("the caller's time limit")

    child = "import os, time; print(os.getpid(), flush=True); time.sleep(60)"
    log = tmp_path / "child.log"
    previous = signal.signal(signal.SIGALRM, limit)
    signal.setitimer(signal.ITIMER_REAL, 2.0)
    start = time.monotonic()
    try:
        run_logged([sys.executable, "-c", child], log, echo=False)
    except TimeoutError:
        pass
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert time.monotonic() - start < 20, "the caller waited for the child"
    pid = int(log.read_text().split()[0])
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return
    raise AssertionError(f"the child {pid} still runs")


def test_training_threads_follow_the_dataloader_workers(tmp_path, monkeypatch):
    import os

    from lerobot_sdp.lerobot_cli import num_workers, training_threads

    config = tmp_path / "c.json"
    config.write_text(json.dumps({"num_workers": 0, "steps": 10}))
    with_config = [f"--config_path={config}", "--steps=5"]
    assert num_workers(with_config) == 0
    assert num_workers([*with_config, "--num_workers=2"]) == 2  # the flag wins over the file
    assert num_workers(["--policy.type=sdp"]) == 4  # LeRobot's default
    cores = len(os.sched_getaffinity(0))
    assert training_threads(with_config) == cores
    assert training_threads([*with_config, "--num_workers=1"]) == 1
    # trainings that run at once share the cores, never below one thread each
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(4)))
    assert training_threads(with_config, concurrent=2) == 2
    assert training_threads(with_config, concurrent=8) == 1


def test_run_logged_gives_the_child_its_threads_unless_the_user_chose(tmp_path, monkeypatch):
    from lerobot_sdp.lerobot_cli import run_logged

    child = "import os; print('threads', os.environ['OMP_NUM_THREADS'], os.environ['MKL_NUM_THREADS'])"
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    run_logged([sys.executable, "-c", child], tmp_path / "a.log", echo=False, threads=2)
    assert "threads 2 2" in (tmp_path / "a.log").read_text()
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    run_logged([sys.executable, "-c", child], tmp_path / "b.log", echo=False, threads=2)
    assert "threads 3 3" in (tmp_path / "b.log").read_text()  # one exported count sets both pools
    monkeypatch.setenv("MKL_NUM_THREADS", "1")
    run_logged([sys.executable, "-c", child], tmp_path / "c.log", echo=False, threads=2)
    assert "threads 3 1" in (tmp_path / "c.log").read_text()  # both exported: each its own


def test_a_training_beside_others_gets_its_share_of_the_cores(tmp_path, monkeypatch):
    import os

    from lerobot_sdp import lerobot_cli

    given = []
    monkeypatch.setattr(lerobot_cli, "run_logged", lambda cmd, log, echo, threads=1: given.append(threads))
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(4)))
    for concurrent in (1, 2):
        lerobot_cli.train(
            tmp_path / f"t{concurrent}", ["--num_workers=0"], 1, tmp_path / "log", concurrent=concurrent
        )
    assert given == [4, 2]


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ("fpu avx2 avx512f avx512_bf16 avx512_vnni", "avx512_bf16"),  # Zen 4, Sapphire Rapids
        ("fpu avx2 amx_bf16 amx_tile", "amx_bf16"),
        ("fpu avx2 fma avx512f", None),  # Zen 3 has no avx512 at all; Skylake-X no bf16
        ("fpu avx512_bf16x", None),  # whole flags only
    ],
)
def test_native_bf16_is_read_from_the_cpus_flags(tmp_path, flags, expected):
    from lerobot_sdp.lerobot_cli import native_bf16_flag

    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(f"processor\t: 0\nmodel name\t: CPU\nflags\t\t: {flags}\n\nprocessor\t: 1\n")
    assert native_bf16_flag(cpuinfo) == expected
    assert native_bf16_flag(tmp_path / "absent") is None  # not Linux: no bf16 claimed


def test_precision_flags_turn_bf16_on_for_cpu_trainings_on_native_bf16_only(tmp_path, monkeypatch):
    from lerobot_sdp import lerobot_cli

    config = tmp_path / "c.json"
    config.write_text(json.dumps({"policy": {"type": "sdp"}}))
    chosen = tmp_path / "amp.json"
    chosen.write_text(json.dumps({"policy": {"type": "sdp", "use_amp": False}}))
    cpu = [f"--config_path={config}", "--policy.device=cpu"]

    def flags(args, precision="auto"):
        return lerobot_cli.precision_flags(args, precision)[0]

    monkeypatch.setattr(lerobot_cli, "native_bf16_flag", lambda: "avx512_bf16")
    assert flags(cpu) == ["--policy.use_amp=true"]
    assert flags([f"--config_path={config}", "--policy.device=cuda"]) == []  # LeRobot's own choice there
    assert flags([f"--config_path={config}"]) == []  # no device named: LeRobot picks one
    assert flags([*cpu, "--policy.use_amp=false"]) == []  # the user's flag stands
    assert flags([f"--config_path={chosen}", "--policy.device=cpu"]) == []  # so does the config's
    assert flags(cpu, "fp32") == ["--policy.use_amp=false"]
    monkeypatch.setattr(lerobot_cli, "native_bf16_flag", lambda: None)
    assert flags(cpu) == []  # emulated bf16 is slower than fp32
    assert flags(cpu, "bf16") == ["--policy.use_amp=true"]


def test_a_new_training_gets_the_precision_and_a_resumed_one_keeps_its_own(tmp_path, monkeypatch):
    from lerobot_sdp import lerobot_cli

    commands = []
    monkeypatch.setattr(lerobot_cli, "run_logged", lambda cmd, log, echo, threads=1: commands.append(cmd))
    monkeypatch.setattr(lerobot_cli, "native_bf16_flag", lambda: "amx_bf16")
    lerobot_cli.train(tmp_path / "new", ["--policy.device=cpu"], 10, tmp_path / "log", precision="auto")
    assert "--policy.use_amp=true" in commands[-1]
    lerobot_cli.train(tmp_path / "plain", ["--policy.device=cpu"], 10, tmp_path / "log")
    assert not any("use_amp" in a for a in commands[-1])  # no precision asked: the config's
    state = lerobot_cli.last_checkpoint(tmp_path / "old") / "training_state"
    state.mkdir(parents=True)
    (state / "training_step.json").write_text(json.dumps({"step": 5}))
    (state.parent / "pretrained_model").mkdir()
    (state.parent / "pretrained_model" / "train_config.json").write_text(json.dumps({"num_workers": 0}))
    lerobot_cli.train(tmp_path / "old", ["--policy.device=cpu"], 10, tmp_path / "log", precision="fp32")
    assert "--resume=true" in commands[-1] and not any("use_amp" in a for a in commands[-1])


def test_the_trained_precision_is_read_from_the_saved_config(tmp_path):
    from lerobot_sdp.lerobot_cli import trained_precision

    (tmp_path / "config.json").write_text(json.dumps({"type": "sdp", "use_amp": True}))
    assert trained_precision(tmp_path) == "bf16 autocast"
    (tmp_path / "config.json").write_text(json.dumps({"type": "sdp", "use_amp": False}))
    assert trained_precision(tmp_path) == "fp32"
