"""Each of the daemon's OS threads as `status` reports it: its share of a core, and where it is measured,
the longest it waited to run once it was due.

The threads name themselves in the OS (realtime.name_os_thread), so /proc/self/task/<tid>/comm
tells them apart; their CPU time is /proc's utime + stime (clock ticks: 10 ms on most kernels, so a
share over CPU_WINDOW_S is good to about 0.2 % of a core). Threads of one name are summed (Zenoh's
runtime threads, and any thread still called after the interpreter).

A thread is due when its deadline passes (the control tick) or when what it waits for arrives (the
estimator's batch of IMU samples). The wait from then until it runs Python again is the OS
scheduler's and, mostly, the GIL's: a thread that wakes must take the GIL from whichever thread
holds it, which lets go only every sys.getswitchinterval() or at its next blocking call. That is
the figure a starved thread shows first (`wake_ms_max`, the largest over the last WAKE_WINDOW_S).
"""
from __future__ import annotations

import collections
import os
import time

CPU_WINDOW_S = 5.0             # s, the window a CPU share is measured over
SAMPLE_EVERY_S = 1.0           # s, how often the main thread reads /proc (some fifteen small reads)
WAKE_WINDOW_S = 5              # s, the window the largest wake-up wait is kept over (whole seconds)
CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


class WakeStats:
    """The longest wait to run after a thread was due, over the last WAKE_WINDOW_S (per-second maxima:
    written by its thread, read by the main thread)."""

    def __init__(self):
        self._sec = [-1] * WAKE_WINDOW_S
        self._max = [0.0] * WAKE_WINDOW_S

    def note(self, late_s: float, now: float) -> None:
        sec = int(now)
        i = sec % WAKE_WINDOW_S
        if self._sec[i] != sec:
            self._max[i] = late_s
            self._sec[i] = sec
        elif late_s > self._max[i]:
            self._max[i] = late_s

    def max_ms(self, now: float) -> float | None:
        recent = [m for s, m in zip(self._sec, self._max) if s > now - WAKE_WINDOW_S - 1]
        return round(1e3 * max(recent), 3) if recent else None


def read_threads_cpu_s(task_dir: str = "/proc/self/task") -> dict[str, float]:
    """CPU seconds per OS thread name (threads of one name summed); {} where /proc is not there."""
    out: dict[str, float] = collections.defaultdict(float)
    try:
        tids = os.listdir(task_dir)
    except OSError:
        return {}
    for tid in tids:
        try:
            with open(f"{task_dir}/{tid}/comm", encoding="utf-8", errors="replace") as f:
                name = f.read().strip()
            with open(f"{task_dir}/{tid}/stat", encoding="ascii", errors="replace") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[name] += (int(fields[11]) + int(fields[12])) / CLK_TCK
        except (OSError, IndexError, ValueError):      # a thread that ended between the listing and the read
            continue
    return dict(out)


class ThreadUsage:
    """Per OS thread: its CPU share of one core over the last CPU_WINDOW_S, and the wake-up waits of the
    threads that measure theirs (`wake`: thread name -> WakeStats). The main thread samples it."""

    def __init__(self, wake: dict[str, WakeStats] | None = None, task_dir: str = "/proc/self/task"):
        self.wake = dict(wake or {})
        self.task_dir = task_dir
        self._samples: collections.deque = collections.deque()
        self._next = -float("inf")

    def sample(self, now: float) -> None:
        """Read /proc at most every SAMPLE_EVERY_S; keeps what spans CPU_WINDOW_S."""
        if now < self._next:
            return
        self._next = now + SAMPLE_EVERY_S
        self._samples.append((now, read_threads_cpu_s(self.task_dir)))
        while len(self._samples) > 2 and now - self._samples[1][0] >= CPU_WINDOW_S:
            self._samples.popleft()

    def snapshot(self, now: float | None = None) -> dict[str, dict]:
        """{thread name: {"cpu_pct": share of one core in %, "wake_ms_max": ms where measured}}, the
        busiest first; {} before two samples."""
        now = time.monotonic() if now is None else now
        if len(self._samples) < 2:
            return {}
        (t0, cpu0), (t1, cpu1) = self._samples[0], self._samples[-1]
        span = t1 - t0
        out = {}
        for name in sorted(cpu1, key=lambda n: cpu0.get(n, 0.0) - cpu1[n]):
            row = {"cpu_pct": round(100.0 * max(cpu1[name] - cpu0.get(name, 0.0), 0.0) / span, 1)}
            if name in self.wake:
                row["wake_ms_max"] = self.wake[name].max_ms(now)
            out[name] = row
        return out
