"""denoisers.training.run_clock: the seconds a process ran, a kill -STOP ... -CONT pause left out (the reference is the
pause the parent timed), a sleep and a long GIL-holding computation counted as running."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from denoisers.training.run_clock import RunClock

REPO_ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import json, sys, time
from denoisers.training.run_clock import RunClock
clock = RunClock().start()
started = time.perf_counter()
print("ready", flush=True)
while time.perf_counter() - started < 7.0:      # busy: the process uses its CPU
    sum(range(1000))
wall = time.perf_counter() - started
print(json.dumps({"seconds": clock.seconds(), "stopped": clock.stopped_seconds, "wall": wall}), flush=True)
"""


def test_a_stop_is_left_out() -> None:
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT,
                             env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
    assert child.stdout.readline().strip() == "ready"
    time.sleep(1.0)
    child.send_signal(signal.SIGSTOP)
    stopped_at = time.perf_counter()
    time.sleep(4.0)
    child.send_signal(signal.SIGCONT)
    paused = time.perf_counter() - stopped_at
    out = json.loads(child.stdout.readline())
    assert child.wait(timeout=60) == 0
    # The clock leaves out the pause less at most one tick (the stop began after its last sample).
    assert paused - 0.6 <= out["stopped"] <= paused + 0.3
    assert out["seconds"] == pytest.approx(out["wall"] - out["stopped"], abs=0.05)


def test_sleeping_and_holding_the_gil_count_as_running() -> None:
    """A sleep uses no CPU but the sampling thread keeps sampling; a regular expression that backtracks for seconds
    holds the GIL, so no sample is taken, but the process uses CPU: neither is a stop."""
    with RunClock() as clock:
        time.sleep(2.5)
        n, took = 20, 0.0
        while took < 2.5 and n < 40:                 # exponential backtracking: each character doubles the time
            started = time.perf_counter()
            re.match(r"(a+)+$", "a" * n + "b")
            took = time.perf_counter() - started
            n += 1
        assert took >= 2.5
        assert clock.stopped_seconds == 0.0
        assert clock.seconds() >= 5.0


def test_tick_and_gap_are_checked() -> None:
    with pytest.raises(ValueError, match="2 tick_s < min_gap_s"):
        RunClock(tick_s=1.0, min_gap_s=1.5)
