"""This host's real-time facts, and a readiness check's record.

The daemon reads them to run its control thread under SCHED_FIFO (runtime.realtime); `tecdard
doctor` reports them; a robot backend's or an IMU source's own `checks()` say, in the same `Check`
records, whether this host can reach its device.
"""
from __future__ import annotations

import os
import pathlib
import platform
import resource
import signal
import threading
from dataclasses import dataclass


@dataclass(frozen=True)
class Check:
    """One line of `tecdard doctor`: a check's name, its status (pass | warn | fail | skip), what it
    found and, for anything but a pass, the fix."""
    name: str
    status: str
    detail: str
    fix: str | None = None

    def lines(self) -> list[str]:
        out = [f"{self.status.upper():4}  {self.name}: {self.detail}"]
        if self.fix and self.status != "pass":
            out.append(f"      fix: {self.fix}")
        return out


def check_rt_kernel(sys_realtime: str = "/sys/kernel/realtime", version: str | None = None) -> Check:
    """Whether this kernel is PREEMPT_RT (its /sys flag or its version string)."""
    version = platform.uname().version if version is None else version
    try:
        flag = pathlib.Path(sys_realtime).read_text().strip() == "1"
    except OSError:
        flag = False
    if flag or "PREEMPT_RT" in version:
        return Check("real-time kernel", "pass", f"PREEMPT_RT ({version[:60]})")
    return Check("real-time kernel", "warn", f"not PREEMPT_RT ({version[:60]}): a 20 ms tick can be late "
                 "by milliseconds under load",
                 "boot a real-time kernel (Debian: linux-image-rt-amd64; Ubuntu: `pro enable realtime-kernel`)")


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


OS_THREAD_NAME_CHARS = 15      # Linux keeps 15 characters of a thread's name (TASK_COMM_LEN 16)
PR_SET_NAME = 15


def name_os_thread(name: str) -> bool:
    """Give the calling thread its name in the OS too (prctl PR_SET_NAME), so that `top -H`, `ps -L` and
    /proc/<pid>/task/*/comm show which thread uses the CPU; Python's own names stay inside Python.
    Best effort: False where the OS does not take it."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_NAME, name[:OS_THREAD_NAME_CHARS].encode("ascii", "replace"), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def without_ctrl_c(target, *args) -> None:
    """A child process's entry (the arm's link, the simulation, the uploader): the terminal's Ctrl-C, which
    reaches the whole foreground process group, is the daemon's to act on. The daemon holds the arm
    first and then closes its children; a child interrupted under it left the hold without its link
    and three tracebacks in the log after "tecdard stopped". SIGTERM keeps its default: the daemon's
    own `terminate` of a child that does not close."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    target(*args)
