"""The `wrist` task: the gripper turned in place about each of its own axes, for the mount's calibration.

About TCP x, then y, then z: +amplitude, -2 amplitude, +amplitude at `rate`, with ramps of
RAMP_S, the TCP held where it started. What `tecdard calibrate-mount --live` records and fits:
the gyro against the arm's own rate about every axis. Nothing may touch the tool meanwhile, so a
contact onset fails the task.
"""
from __future__ import annotations

import enum
import math

import numpy as np

from tecdard.control.geometry import rotvec_to_matrix
from tecdard.control.tasks import Motion, Task, TickInput

RAMP_S = 0.05                   # the rate's ramps (the clock offset shows where the rate changes)
LEGS = (1.0, -2.0, 1.0)         # each axis: out, through, back, in amplitudes
PAUSE_S = 0.3                   # still between axes


def _leg_angle(s: float, length: float, rate: float) -> float:
    """The angle (rad, >= 0) s seconds into a leg of `length` rad at `rate`, trapezoidal with RAMP_S ramps."""
    ramp = min(RAMP_S, length / rate)
    cruise = length / rate - ramp
    total = cruise + 2.0 * ramp
    s = min(max(s, 0.0), total)
    peak = rate if cruise > 0 else length / ramp
    if s < ramp:
        return 0.5 * peak / ramp * s * s
    if s < ramp + cruise:
        return 0.5 * peak * ramp + peak * (s - ramp)
    d = total - s
    return length - 0.5 * peak / ramp * d * d


class WristTask(Task):
    """Turn the wrist about each TCP axis in turn (module doc)."""

    class Phase(enum.StrEnum):
        TURN = "turn"

    kind = "wrist"

    def __init__(self, task_id: str, amplitude_rad: float, rate_rad_s: float):
        super().__init__(task_id, np.array([1.0, 0.0, 0.0]), 0.0)
        self.amplitude = amplitude_rad
        self.rate = rate_rad_s
        self.schedule = self._schedule()          # (start s, axis, sign, length rad, duration s)
        self.duration_s = self.schedule[-1][0] + self.schedule[-1][4] + PAUSE_S
        self._t0 = 0.0

    def _schedule(self) -> list:
        out, t = [], 0.0
        for axis in range(3):
            for leg in LEGS:
                length = abs(leg) * self.amplitude
                dur = length / self.rate + min(RAMP_S, length / self.rate)
                out.append((t, axis, math.copysign(1.0, leg), length, dur))
                t += dur
            t += PAUSE_S
        return out

    def rotvec_at(self, s: float) -> np.ndarray:
        """The tool's turn from its start pose, TCP frame (rad), s seconds into the task: the axes
        before the current one are back at zero."""
        v = np.zeros(3)
        for start, axis, sign, length, dur in self.schedule:
            if s < start:
                break
            v[axis] += sign * _leg_angle(s - start, length, self.rate)
        return v

    def _started(self, inp: TickInput) -> None:
        self._t0 = inp.t
        self._enter(self.Phase.TURN, inp.t)

    def _step_turn(self, inp: TickInput) -> Motion | None:
        st, s = self.status, inp.t - self._t0
        if inp.contact.tracking and inp.contact.onset_t is not None:
            self._fail("a contact onset while the wrist turned: calibrate the mount in free air")
            return None
        st.progress = min(max(s / self.duration_s, 0.0), 1.0)
        if s >= self.duration_s and inp.planner_at_rest:
            self._done({"axes": 3, "amplitude_deg": math.degrees(self.amplitude),
                        "rate_deg_s": math.degrees(self.rate), "duration_s": s})
            return None
        if self._timed_out(inp.t, self.duration_s):
            self._fail("the wrist's turns did not finish in time")
            return None
        # the servo holds the orientation given now, with its rate as feed-forward (control.servo); the
        # TCP's position stays where it started
        v = self.rotvec_at(s)
        rate = (self.rotvec_at(s + 0.005) - self.rotvec_at(s - 0.005)) / 0.01
        return Motion(self.p_start.copy(), np.zeros(3), self.R_hold @ rotvec_to_matrix(v), w=self.R_hold @ rate)

    STEPS = {Phase.TURN: _step_turn}
