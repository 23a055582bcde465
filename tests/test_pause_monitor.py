"""The runner's pause monitor notes when its whole process stood still (here: SIGSTOP for 0.6 s)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

CHILD = """
import json, sys
from sitl.pause_monitor import PauseMonitor
monitor = PauseMonitor().start()
print("ready", flush=True)
sys.stdin.readline()
monitor.stop()
print(json.dumps([p.length_s for p in monitor.pauses()]), flush=True)
"""


def test_a_stopped_process_is_noted_as_a_pause_and_a_running_one_is_not() -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "ready"
    time.sleep(0.5)  # running: nothing to note
    child.send_signal(signal.SIGSTOP)
    time.sleep(0.6)
    child.send_signal(signal.SIGCONT)
    time.sleep(0.2)
    out, _ = child.communicate("\n", timeout=10)
    lengths = json.loads(out)
    assert len(lengths) == 1 and 0.55 <= lengths[0] <= 1.5, lengths
