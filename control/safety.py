"""Safety checks of the control tick, as pure functions: measurements and limits in, a stop cause or None out.

Two kinds of finding:
- faults of the sensor (`imu_stale`, `imu_saturated`): they hold until the condition clears, and
  while one holds no task is accepted;
- protective stops of the running task (force, rotation, divergence, contact_jump, tracking,
  workspace), each a `StopCause`.

A task adds checks of its own as `reactions` (franky attaches reactions to motions the same way):
each is called with the same `SafetyInput` after the generic checks and may return a StopCause.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

IMU_STARTUP_GRACE_S = 1.0     # no stale-IMU fault before the first sample until this long after start
# A tick that starts this late means the daemon itself was stalled (the machine, the GIL): the IMU's
# samples may be waiting in the acquisition thread's queue, so staleness is judged on the next tick
# (once; a second late tick judges it all the same).
STALE_JUDGE_LATE_S = 0.01


@dataclass(frozen=True)
class SafetyLimits:
    imu_stale_s: float = 0.05
    max_force_n: float = 15.0
    max_rotation_deg: float = 95.0
    max_nis_ratio: float = 10.0
    max_contact_jump_m: float = 0.02
    max_tracking_error_m: float = 0.01
    workspace_min: tuple = (-1.0, -1.0, 0.0)
    workspace_max: tuple = (1.0, 1.0, 1.5)


@dataclass(frozen=True)
class StopCause:
    cause: str                 # the `protective_stop` event's cause (docs/zenoh-api.md)
    message: str
    details: dict = field(default_factory=dict)    # the measured value: force_n, angle_deg, nis_ratio, jump_m


@dataclass(frozen=True)
class SafetyInput:
    """What a tick knows when it checks a running task."""
    contact_force: np.ndarray | None  # force of the world on the TCP, world, N (None: not measured)
    est: object | None                # the newest ContactEstimate of this task's episode (None: none yet)
    prev_est: object | None           # the one the previous tick saw


Reaction = Callable[[SafetyInput], "StopCause | None"]


# -- the IMU ------------------------------------------------------------------------

@dataclass(frozen=True)
class Staleness:
    stale: str | None          # the fault message when the stream is stale, else None
    deferred: bool             # judged on the next tick (this one started late)


def imu_staleness(now: float, total: int, last_t: float, since_boot_s: float, late_s: float, deferred: bool,
                  limits: SafetyLimits) -> Staleness:
    """Whether the IMU stream is stale at `now`. `total` samples so far, the newest at `last_t`;
    `late_s`: how late this tick started; `deferred`: the previous tick put its judgement off."""
    if total == 0 and since_boot_s < IMU_STARTUP_GRACE_S:
        return Staleness(None, False)           # the first samples are still on their way
    age = now - last_t
    if age <= limits.imu_stale_s:
        return Staleness(None, False)
    if late_s > STALE_JUDGE_LATE_S and not deferred:
        return Staleness(None, True)            # our own stall: judge on the next tick
    limit_ms = limits.imu_stale_s * 1e3
    if total == 0:
        return Staleness(f"no IMU sample since the start, {since_boot_s * 1e3:.0f} ms ago (limit {limit_ms:.0f} ms)",
                          False)
    return Staleness(f"no IMU sample for {age * 1e3:.0f} ms (limit {limit_ms:.0f} ms)", False)


def state_staleness(now: float, state_t: float, limit_s: float, late_s: float, deferred: bool) -> Staleness:
    """Whether the robot's newest state (measured at `state_t`, the controller's clock mapped to
    ours) is older than `limit_s` at `now`; our own stall is judged on the next tick, as for the IMU."""
    age = now - state_t
    if age <= limit_s:
        return Staleness(None, False)
    if late_s > STALE_JUDGE_LATE_S and not deferred:
        return Staleness(None, True)
    return Staleness(f"the robot's newest state is {age * 1e3:.0f} ms old (limit {limit_s * 1e3:.0f} ms)", False)


def imu_saturation(now: float, saturated_since: float | None, limits: SafetyLimits) -> str | None:
    """A stream clipped at full scale for longer than imu_stale_s is a sensor fault (stuck, or
    overloaded): no contact can be measured from it. A single clipped impact is not."""
    if saturated_since is not None and now - saturated_since > limits.imu_stale_s:
        return (f"the IMU has read full scale for {(now - saturated_since) * 1e3:.0f} ms "
                f"(limit {limits.imu_stale_s * 1e3:.0f} ms)")
    return None


class SensorWatch:
    """The sensors' faults (imu_stale, imu_saturated, robot_stale, and the robot backend's own) as
    state: each holds from when its condition is found until it clears. The updates return what
    changed, as (event kind, code, message) with kind `fault` or `fault_cleared`; a new fault is
    also a protective stop of the running task."""

    def __init__(self, limits: SafetyLimits, t_boot: float):
        self.limits = limits
        self.t_boot = t_boot
        self.faults: dict[str, str] = {}
        self._stale_deferred = False
        self._state_deferred = False
        self._robot_codes: set[str] = set()

    def update(self, now: float, total: int, last_t: float, late_s: float,
               saturated_since: float | None) -> list[tuple[str, str, str]]:
        verdict = imu_staleness(now, total, last_t, now - self.t_boot, late_s, self._stale_deferred, self.limits)
        self._stale_deferred = verdict.deferred
        changes = self._set("imu_stale", verdict.stale, keep=verdict.deferred)
        if verdict.stale is not None and "imu_stale" in self.faults:
            self.faults["imu_stale"] = verdict.stale         # said as it stands: "for 2300 ms", not the first 58
        changes += self._set("imu_saturated", imu_saturation(now, saturated_since, self.limits),
                             keep=saturated_since is not None)
        return changes

    def update_state_age(self, now: float, state_t: float, limit_s: float, late_s: float) -> list[tuple[str, str, str]]:
        """`robot_stale` while the robot's newest state is older than `limit_s` (its backend's budget)."""
        verdict = state_staleness(now, state_t, limit_s, late_s, self._state_deferred)
        self._state_deferred = verdict.deferred
        return self._set("robot_stale", verdict.stale, keep=verdict.deferred)

    def update_robot(self, current: dict[str, str]) -> list[tuple[str, str, str]]:
        """The robot backend's faults that hold now (code -> message): new ones are raised, those of
        the backend's that no longer hold are cleared."""
        changes = []
        for code in [c for c in self._robot_codes if c not in current]:
            self._robot_codes.discard(code)
            changes += self._set(code, None, keep=False)
        for code, message in current.items():
            self._robot_codes.add(code)
            changes += self._set(code, message, keep=False)
        return changes

    def _set(self, code: str, message: str | None, keep: bool) -> list[tuple[str, str, str]]:
        if message is not None and code not in self.faults:
            self.faults[code] = message
            return [("fault", code, message)]
        if message is None and code in self.faults and not keep:
            return [("fault_cleared", code, self.faults.pop(code))]
        return []


# -- a running task ---------------------------------------------------------------

def check_task(inp: SafetyInput, limits: SafetyLimits, reactions: tuple = ()) -> StopCause | None:
    """Force, then the estimator's checks (rotation, divergence, contact jumps), then the task's own."""
    if inp.contact_force is not None:
        f = float(np.linalg.norm(inp.contact_force))
        if f > limits.max_force_n:
            return StopCause("force", f"TCP force {f:.1f} N over the limit {limits.max_force_n:.1f} N", {"force_n": f})
    cause = _check_estimate(inp.est, inp.prev_est, limits) if inp.est is not None else None
    if cause is not None:
        return cause
    for reaction in reactions:
        cause = reaction(inp)
        if cause is not None:
            return cause
    return None


def _check_estimate(est, prev, limits: SafetyLimits) -> StopCause | None:
    angle = math.degrees(est.angle_rad)
    if angle > limits.max_rotation_deg:
        return StopCause("rotation", f"object turned {angle:.1f} deg, over the limit {limits.max_rotation_deg:.1f} deg",
                         {"angle_deg": angle})
    if est.nis_ratio is not None and est.nis_ratio > limits.max_nis_ratio:
        # the measurements stopped fitting the contact model: a slip, a moving hinge, a bad sensor
        return StopCause("divergence", f"estimator innovations {est.nis_ratio:.0f}x their expected size "
                                       f"(limit {limits.max_nis_ratio:.0f}x)", {"nis_ratio": est.nis_ratio})
    if prev is not None and prev.onset_t == est.onset_t and prev.converged and prev is not est:
        d = est.p - prev.p
        if est.axis is not None:
            d = d - float(np.dot(d, est.axis)) * est.axis     # along a line contact: unobservable
        jump = float(np.linalg.norm(d))
        if jump > limits.max_contact_jump_m:
            return StopCause("contact_jump", f"contact estimate moved {jump * 1e3:.1f} mm in one tick "
                                             f"(limit {limits.max_contact_jump_m * 1e3:.0f} mm)", {"jump_m": jump})
    return None


def check_motion(p_target: np.ndarray, p_plan: np.ndarray, p_measured: np.ndarray,
                 limits: SafetyLimits) -> StopCause | None:
    """The arm follows its plan, and the task's next target stays inside the workspace box."""
    lag = float(np.linalg.norm(p_plan - p_measured))
    if lag > limits.max_tracking_error_m:
        # the arm is not following (a joint at its limit, an unreachable target, a collision)
        return StopCause("tracking", f"TCP {lag * 1e3:.1f} mm from its planned position "
                                     f"(limit {limits.max_tracking_error_m * 1e3:.0f} mm)")
    if np.any(p_target < limits.workspace_min) or np.any(p_target > limits.workspace_max):
        return StopCause("workspace", f"target {np.round(p_target, 4).tolist()} leaves the workspace box")
    return None
