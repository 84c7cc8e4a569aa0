"""Running LeRobot's commands as subprocesses (`lerobot_sdp.lerobot_cli`)."""

import subprocess
import sys

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
