"""Every robot state is checked before anything uses it: a controller's reading is input too.

A state a backend's link receives goes through its `StateCheck` before it is published to the
daemon's threads (robots.child_link.ChildLink._publish). A state that fails is dropped: its values
never reach FK, the servo, the estimator or a recording, and the backend holds the fault
`robot_state`, naming the reading, until states have passed for FAULT_HOLD_S. The control tick
raises it as any robot fault: a protective stop, and tasks refused while it holds.

What a state must be:
- finite: joints, rates, and the TCP pose, twist and force where the robot reports them;
- every joint within the model's range (robots.model: the URDF's, FR3's datasheet's) plus
  `robot.joint_limit_margin_rad`: an encoder cannot read beyond the hard stops;
- no joint further from the last accepted state than its speed limit allows in the time between
  them (JUMP_SPEED_FACTOR x the limit, plus JUMP_SLACK_RAD for encoder noise and clock jitter);
- every joint rate within JUMP_SPEED_FACTOR x its limit;
- the TCP pose, where reported, a rotation and a position within MAX_REACH_M of the base.

How old the newest state may be is the other half (`robot.max_state_age_s`, per backend: see
RobotBackend.state_age_s): the control tick watches it (control.safety.SensorWatch) and never
servos from an older state.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from tecdard.options import option

DEFAULT_LIMIT_MARGIN_RAD = 0.05   # a joint read this far past its range: refused (about 3 degrees)
JUMP_SPEED_FACTOR = 1.5           # a joint may move up to this x its speed limit between two states
JUMP_SLACK_RAD = 0.005            # ... plus this (encoder noise, the clock's jitter between states)
MIN_STATE_DT_S = 0.001            # two states are at least this far apart for the jump's allowance
FAULT_HOLD_S = 0.5                # the fault holds until states have passed for this long
MAX_REACH_M = 5.0                 # no arm's TCP is further from its base
ROTATION_TOL = 1e-3               # |R^T R - I| of a reported TCP rotation


@dataclass(frozen=True)
class StateOptions:
    """The `robot` section's options for the states every backend checks: how far past its range a joint
    may read, and how old the newest state may be."""
    max_state_age_s: float = option(0.05, "the newest robot state older than this is robot_stale (a protective "
                                          "stop) and the servo holds; a backend's own default (the simulator's: "
                                          "0.1 s)", unit="s", above=0.0, maxval=1.0)
    joint_limit_margin_rad: float = option(DEFAULT_LIMIT_MARGIN_RAD, "a joint read further past its range is "
                                                                     "refused (robot_state)", unit="rad",
                                           minval=0.0, maxval=0.5)


class StateCheck:
    """The checks of one robot's states, and the fault they hold. `admit` runs on the link's reader
    thread; `fault` (a message, or None) is read by the control tick; `reset` starts afresh for a
    new link (no previous state to measure a jump from)."""

    def __init__(self, model, source: str, margin_rad: float = DEFAULT_LIMIT_MARGIN_RAD, clock=time.monotonic):
        self.names = [str(n) for n in model.model.names[1:]][:model.nq]
        self.q_min = np.asarray(model.q_min, float) - margin_rad
        self.q_max = np.asarray(model.q_max, float) + margin_rad
        self.qd_max = np.asarray(model.qd_max, float)
        self._qd_limit = JUMP_SPEED_FACTOR * self.qd_max      # rad/s, a joint rate beyond is no reading
        self.margin_rad = margin_rad
        self.source = source                  # who reports the states, for the message ("UR controller 10.0.0.2")
        self.clock = clock
        self.fault: str | None = None
        self.refused = 0                      # states refused so far
        self.seen_t = -math.inf               # when the newest state received was measured, refused or not
        self._prev = None                     # the last accepted JointState
        self._bad_t = -math.inf               # when the last state was refused (our clock)

    def reset(self) -> None:
        self._prev = None
        self.seen_t = -math.inf

    def admit(self, js) -> bool:
        """True when the state may be used; False (and the fault set) when it may not."""
        problem = self.problem(js)
        now = self.clock()
        if math.isfinite(js.t):
            self.seen_t = max(self.seen_t, js.t)
        if problem is not None:
            self.refused += 1
            self._bad_t = now
            self.fault = f"{self.source}: state refused: {problem}"
            return False
        self._prev = js
        if self.fault is not None and now - self._bad_t >= FAULT_HOLD_S:
            self.fault = None
        return True

    def problem(self, js) -> str | None:
        """What is wrong with a state (one line naming the reading), or None."""
        with np.errstate(over="ignore", invalid="ignore"):     # a hostile reading is refused, not warned of
            return self._problem(js)

    def _problem(self, js) -> str | None:
        q, qd = np.asarray(js.q, float), np.asarray(js.qd, float)
        n = len(self.names)
        if q.shape != (n,) or qd.shape != (n,):
            return f"{q.size} joint positions and {qd.size} rates, expected {n} each"
        # Each check is first made whole (a state comes 500-1000 times a second, and nearly every one
        # passes); only a state that fails one is looked at joint by joint, for the message.
        if not (_finite(q) and _finite(qd)):
            for what, values, unit in (("position", q, "rad"), ("rate", qd, "rad/s")):
                bad = ~np.isfinite(values)
                if bad.any():
                    j = int(np.argmax(bad))
                    return f"{self.names[j]} {what} reads {values[j]} {unit}"
        if not math.isfinite(js.t):
            return f"its time reads {js.t}"
        if not ((q >= self.q_min).all() and (q <= self.q_max).all()):
            out = (q < self.q_min) | (q > self.q_max)
            j = int(np.argmax(out))
            return (f"{self.names[j]} at {q[j]:.3f} rad, outside its range [{self.q_min[j] + self.margin_rad:.3f}, "
                    f"{self.q_max[j] - self.margin_rad:.3f}] rad (+{self.margin_rad:g} rad margin)")
        if not (np.abs(qd) <= self._qd_limit).all():
            j = int(np.argmax(np.abs(qd) > self._qd_limit))
            return f"{self.names[j]} rate {qd[j]:.3f} rad/s, over {JUMP_SPEED_FACTOR:g} x its limit {self.qd_max[j]:.3f} rad/s"
        problem = self._jump(js, q)
        if problem is not None:
            return problem
        return _tcp_problem(js)

    def _jump(self, js, q: np.ndarray) -> str | None:
        prev = self._prev
        if prev is None:
            return None
        dt = max(js.t - prev.t, MIN_STATE_DT_S)
        allowed = JUMP_SPEED_FACTOR * self.qd_max * dt + JUMP_SLACK_RAD
        step = np.abs(q - np.asarray(prev.q, float))
        if (step <= allowed).all():
            return None
        j = int(np.argmax(step > allowed))
        return (f"{self.names[j]} jumped {step[j]:.3f} rad in {dt * 1e3:.1f} ms (its speed limit "
                f"{self.qd_max[j]:.2f} rad/s allows {allowed[j]:.3f} rad)")


def _finite(a: np.ndarray) -> bool:
    """Every element finite, in one sum: a sum of finite values is finite unless it overflows, and
    then the caller looks element by element (never a false pass)."""
    return math.isfinite(float(np.add.reduce(a, axis=None)))


EYE3 = np.eye(3)


def _tcp_problem(js) -> str | None:
    """The TCP pose, twist, force and grip force a robot reports: finite, and a pose that is one."""
    for what, value, unit in (("TCP twist", js.tcp_twist, "m/s and rad/s"), ("TCP force", js.tcp_force, "N"),
                              ("grip force", js.grip_force, "N")):
        if value is not None:
            value = np.asarray(value, float)
            if not _finite(value) and not np.all(np.isfinite(value)):
                return f"{what} reads {_show(value)} {unit}"
    pose = js.tcp_pose
    if pose is None:
        return None
    pose = np.asarray(pose, float)
    if pose.shape != (4, 4):
        return f"TCP pose of shape {pose.shape}, not 4 x 4"
    R, p = pose[:3, :3], pose[:3, 3]
    if not _finite(pose[:3]):
        if not np.all(np.isfinite(p)):
            return f"TCP position reads {_show(p)} m"
        if not np.all(np.isfinite(R)):
            return "TCP rotation reads no rotation (non-finite or not orthonormal)"
    if np.abs(R.T @ R - EYE3).max() > ROTATION_TOL:
        return "TCP rotation reads no rotation (non-finite or not orthonormal)"
    reach = float(np.linalg.norm(p))
    if reach > MAX_REACH_M:
        return f"TCP pose {reach:.2f} m from the base (no arm reaches beyond {MAX_REACH_M:g} m)"
    return None


def _show(value) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(value, float).ravel()) + "]"
