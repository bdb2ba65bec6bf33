"""Real-time scheduling for the control thread (`control.rt_priority`), and what the host allows.

Linux applies a scheduling policy per thread: `os.sched_setscheduler(0, ...)` called on a thread
sets that thread's policy only. The control thread asks for SCHED_FIFO at `rt_priority` when it
starts; where the host refuses (RLIMIT_RTPRIO below the priority, no CAP_SYS_NICE, a container),
the daemon logs one line and runs SCHED_OTHER. `tecdard doctor` reports the same facts.
"""
from __future__ import annotations

import logging
import os
import time

import numpy as np

from tecdard.host import set_fifo
from tecdard.runtime.threads import WakeStats

log = logging.getLogger("tecdar")

MAX_RT_PRIORITY = 98          # 99 is the kernel's own watchdog threads' level: never above them
TICK_STATS_WINDOW = 1000      # ticks kept for percentiles
TICK_STATS_RECENT = 250       # ticks of the recent window (5 s at 50 Hz)
TICK_STATS_EVERY = 25         # recompute percentiles every this many ticks


def apply_rt_priority(priority: int | None, what: str = "control thread") -> bool:
    """For the calling thread: SCHED_FIFO where asked and allowed; one log line either way."""
    if priority is None:
        return False
    problem = set_fifo(priority)
    if problem is None:
        log.info("%s runs SCHED_FIFO at priority %d", what, priority)
        return True
    log.warning("control.rt_priority %d: %s; the %s runs SCHED_OTHER", priority, problem, what)
    return False


# The threads the control tick waits on for the GIL: with control.rt_priority they run this much less
# nice than the rest of the host, so that a busy core does not preempt one while it holds the GIL (the
# tick, under SCHED_FIFO, then waits for it all the same). The main thread (telemetry, queries) too.
GIL_THREADS = ("estimator", "imu-acquisition", "proprioception", "ur-link", "franka-link", "sim-link")
GIL_THREAD_NICE = -10


def threads_named(pick, task_dir: str = "/proc/self/task") -> list[int]:
    """The native ids of this process's threads whose OS name (comm) `pick(name)` takes."""
    import pathlib
    tids = []
    for task in pathlib.Path(task_dir).glob("*"):
        try:
            if pick((task / "comm").read_text().strip()):
                tids.append(int(task.name))
        except (OSError, ValueError):
            pass                       # a thread that has ended since
    return tids


def raise_gil_threads(nice: int = GIL_THREAD_NICE, task_dir: str = "/proc/self/task") -> str | None:
    """With control.rt_priority: GIL_THREADS and the main thread at `nice` (Linux: a thread's nice value
    is its own). None when done, else why not (no CAP_SYS_NICE, nor an RLIMIT_NICE that allows it:
    the unit's LimitNICE=)."""
    import threading
    tids = {threading.main_thread().native_id, *threads_named(GIL_THREADS.__contains__, task_dir)}
    for tid in sorted(tids):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except PermissionError:
            return f"nice {nice} refused (needs CAP_SYS_NICE or LimitNICE={nice})"
        except OSError:
            pass                       # a thread that has ended since
    return None


class TickStats:
    """A fixed-rate loop's work and lateness per tick (ms percentiles over the last ticks) and its overruns."""

    def __init__(self):
        self.ticks = 0
        self.overruns = 0
        self._work = np.zeros(TICK_STATS_WINDOW)
        self._late = np.zeros(TICK_STATS_WINDOW)
        self.summary = {}
        self.wake = WakeStats()       # the largest lateness of the last seconds, for `status`'s threads

    def add(self, work_s: float, late_s: float, now: float | None = None) -> None:
        self.wake.note(late_s, time.monotonic() if now is None else now)
        i = self.ticks % TICK_STATS_WINDOW
        self._work[i] = work_s
        self._late[i] = late_s
        self.ticks += 1
        if self.ticks % TICK_STATS_EVERY == 0:
            n = min(self.ticks, TICK_STATS_WINDOW)
            w, lt = self._work[:n] * 1e3, self._late[:n] * 1e3
            self.summary = {
                "ticks": self.ticks, "overruns": self.overruns,
                "work_ms_p50": round(float(np.median(w)), 3), "work_ms_p99": round(float(np.percentile(w, 99)), 3),
                "work_ms_max": round(float(w.max()), 3),
                "late_ms_p50": round(float(np.median(lt)), 3), "late_ms_p99": round(float(np.percentile(lt, 99)), 3),
                "late_ms_max": round(float(lt.max()), 3),
                # the last TICK_STATS_RECENT ticks alone (5 s at 50 Hz): a window's figure, not 20 s's
                "late_ms_p99_recent": round(float(np.percentile(self._recent(self._late), 99)) * 1e3, 3),
            }

    def _recent(self, arr: np.ndarray) -> np.ndarray:
        n = min(self.ticks, TICK_STATS_RECENT)
        idx = (self.ticks - 1 - np.arange(n)) % TICK_STATS_WINDOW
        return arr[idx]

    def snapshot(self) -> dict:
        out = dict(self.summary)
        out["ticks"] = self.ticks
        out["overruns"] = self.overruns
        return out
