"""A clock of the seconds a process ran: wall time less the time it was stopped (``kill -STOP`` ... ``-CONT``).

Long trainings are paused while test suites and benchmarks run beside them (developers' guide), and their elapsed
time and logged steps per second should measure the training, not the pause. A daemon thread samples the wall clock
and the process's CPU time every ``tick_s``. A gap between two samples of at least ``min_gap_s`` is a stop when the
process used less CPU time in it than ``cpu_fraction`` of the gap beyond two ticks (a stopped process uses none; up
to a tick's worth comes from before the stop and after it), and is left out less one tick (the stop began somewhere
after the earlier sample). A long gap in which the process computed (the sampling thread waiting for the GIL, held by
a long native call) counts as running: it uses at least one CPU-second per second. A process the operating system
did not schedule at all for ``min_gap_s`` would count as stopped. Stops shorter than ``min_gap_s`` count as running.
"""
from __future__ import annotations

import threading
import time


class RunClock:
    """Running seconds since :meth:`start` (:meth:`seconds`), stops left out (:attr:`stopped_seconds`).

    ``tick_s`` seconds between samples; ``min_gap_s`` the shortest gap that can be a stop; ``cpu_fraction`` the
    most process CPU time per wall second (beyond two ticks) in a gap that is a stop."""

    def __init__(self, tick_s: float = 0.5, min_gap_s: float = 3.0, cpu_fraction: float = 0.5) -> None:
        if not 0 < 2 * tick_s < min_gap_s:
            raise ValueError(f"RunClock needs 0 < 2 tick_s < min_gap_s, got tick_s {tick_s} and min_gap_s {min_gap_s}")
        self.tick_s, self.min_gap_s, self.cpu_fraction = tick_s, min_gap_s, cpu_fraction
        self.stopped_seconds = 0.0
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = self._last_wall = time.perf_counter()
        self._last_cpu = time.process_time()

    def start(self) -> RunClock:
        """Start counting now (and the sampling thread); returns self."""
        with self._lock:
            self._started = self._last_wall = time.perf_counter()
            self._last_cpu = time.process_time()
            self.stopped_seconds = 0.0
        if self._thread is None:
            self._halt.clear()
            self._thread = threading.Thread(target=self._run, name="run-clock", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the sampling thread (the clock still answers :meth:`seconds`, without noticing later stops)."""
        self._halt.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> RunClock:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        while not self._halt.wait(self.tick_s):
            self._sample()

    def _sample(self) -> float:
        """Take a sample; returns the running seconds at it."""
        with self._lock:
            wall, cpu = time.perf_counter(), time.process_time()
            gap, used = wall - self._last_wall, cpu - self._last_cpu
            if gap >= self.min_gap_s and used < self.cpu_fraction * (gap - 2 * self.tick_s):
                self.stopped_seconds += gap - self.tick_s
            self._last_wall, self._last_cpu = wall, cpu
            return wall - self._started - self.stopped_seconds

    def seconds(self) -> float:
        """Seconds since :meth:`start` that the process was not stopped (a stop just ended is noticed here too)."""
        return self._sample()
