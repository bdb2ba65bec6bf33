"""Real-time scheduling for the control thread (`control.rt_priority`), and what the host allows.

Linux applies a scheduling policy per thread: `os.sched_setscheduler(0, ...)` called on a thread
sets that thread's policy only. The control thread asks for SCHED_FIFO at `rt_priority` when it
starts; where the host refuses (RLIMIT_RTPRIO below the priority, no CAP_SYS_NICE, a container),
the daemon logs one line and runs SCHED_OTHER. `tecdard doctor` reports the same facts.
"""
from __future__ import annotations

import logging
import os
import resource
import threading

import numpy as np

log = logging.getLogger("tecdar")

MAX_RT_PRIORITY = 98          # 99 is the kernel's own watchdog threads' level: never above them


def rtprio_limit() -> tuple[int, int]:
    """(soft, hard) RLIMIT_RTPRIO; RLIM_INFINITY as 99."""
    soft, hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    inf = resource.RLIM_INFINITY
    return (99 if soft == inf else int(soft)), (99 if hard == inf else int(hard))


def set_fifo(priority: int) -> str | None:
    """SCHED_FIFO at `priority` for the calling thread; None, or why the host refused."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return None
    except PermissionError:
        soft, _ = rtprio_limit()
        return (f"SCHED_FIFO {priority} refused (RLIMIT_RTPRIO {soft}, no CAP_SYS_NICE): the unit's "
                f"LimitRTPRIO= or /etc/security/limits.d grants it")
    except OSError as exc:
        return f"SCHED_FIFO {priority} refused: {exc.strerror or exc}"


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


def can_set_fifo(priority: int) -> str | None:
    """Whether SCHED_FIFO at `priority` can be set here, tried on a short-lived thread of its own
    (the caller's scheduling is never touched). None, or why not."""
    out: list[str | None] = []

    def probe():
        problem = set_fifo(priority)
        if problem is None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        out.append(problem)

    t = threading.Thread(target=probe, name="rt-probe")
    t.start()
    t.join(5.0)
    return out[0] if out else "the probe thread did not finish"


TICK_STATS_WINDOW = 1000      # ticks kept for percentiles
TICK_STATS_EVERY = 25         # recompute percentiles every this many ticks


class TickStats:
    """A fixed-rate loop's work and lateness per tick (ms percentiles over the last ticks) and its overruns."""

    def __init__(self):
        self.ticks = 0
        self.overruns = 0
        self._work = np.zeros(TICK_STATS_WINDOW)
        self._late = np.zeros(TICK_STATS_WINDOW)
        self.summary = {}

    def add(self, work_s: float, late_s: float) -> None:
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
            }

    def snapshot(self) -> dict:
        out = dict(self.summary)
        out["ticks"] = self.ticks
        out["overruns"] = self.overruns
        return out
