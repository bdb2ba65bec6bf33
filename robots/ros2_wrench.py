"""The observer's wrench: the arm's own estimate at the TCP as its ROS 2 driver publishes it (geometry_msgs/WrenchStamped
on `ros2.wrench`), checked and kept for the joint states it is taken with. Optional data: a bad message is left out
and said in one line (the first, then every thousandth), never a fault of the arm."""
from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

log = logging.getLogger("tecdar.ros2")

MAX_FORCE_N = 1e4            # no arm's estimate is larger: a message beyond it is not one
MAX_TORQUE_NM = 1e3
MAX_FUTURE_S = 0.5           # a stamp this far ahead of this host's clock is a clock out of sync
SAID_EVERY = 1000


class WrenchTopic:
    """The newest wrench taken, `(t, force, torque)` on the daemon's monotonic clock; `problems` counts those left out."""

    def __init__(self, base_frame: str, stale_s: float):
        self.base_frame, self.stale_s = base_frame, stale_s
        self._lock = threading.Lock()
        self._latest: tuple[float, np.ndarray, np.ndarray] | None = None
        self.problems = 0

    def take(self, msg, problem: str | None, source: bytes | None = None) -> None:
        """The node's handler (Zenoh's thread): one WrenchStamped, or why none could be read."""
        if msg is not None:
            try:
                problem = self._check(msg)
            except Exception as exc:             # the right type with values no driver sends
                problem = f"{type(exc).__name__}: {str(exc)[:120]}"
        if problem is not None:
            self.problems += 1
            if self.problems == 1 or self.problems % SAID_EVERY == 0:
                log.warning("ros2.wrench: %s; left out (%d so far)", problem, self.problems)

    def _check(self, msg) -> str | None:
        frame = msg.header.frame_id
        if frame != self.base_frame:
            return (f"frame_id {frame!r}: only ros2.base_frame {self.base_frame!r} is taken (the daemon has no tf2; "
                    f"republish the wrench in the base frame)")
        w = msg.wrench
        force = np.array([w.force.x, w.force.y, w.force.z], dtype=float)
        torque = np.array([w.torque.x, w.torque.y, w.torque.z], dtype=float)
        if not (np.all(np.isfinite(force)) and np.all(np.isfinite(torque))):
            return "a force or torque that is not finite"
        if np.max(np.abs(force)) > MAX_FORCE_N or np.max(np.abs(torque)) > MAX_TORQUE_NM:
            return f"a force beyond {MAX_FORCE_N:g} N or a torque beyond {MAX_TORQUE_NM:g} N m: no arm's estimate"
        stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        now_wall, now = time.time(), time.monotonic()
        if stamp_s == 0.0:
            return "header.stamp is zero (the publisher must stamp its messages)"
        if stamp_s > now_wall + MAX_FUTURE_S:
            return f"stamped {stamp_s - now_wall:.3f} s in the future (is this host's clock in sync with the publisher's?)"
        with self._lock:
            self._latest = (now - (now_wall - stamp_s), force, torque)
        return None

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(force, torque) for a joint state at `t`: the newest wrench, unless it is stale_s older (or newer) than it."""
        with self._lock:
            latest = self._latest
        if latest is None or not math.isclose(latest[0], t, abs_tol=self.stale_s):
            return None
        return latest[1], latest[2]
