"""The paper's Algorithm 2, stepped by the 20 ms control tick: a short tangential probe, then an arc about
the estimated hinge (rotate), or the same arc length to localise a contact (probe)."""
from __future__ import annotations

import enum
import math

import numpy as np

from tecdard.control.geometry import rotvec_to_matrix, signed_angle, unit
from tecdard.control.tasks import ANGLE_TOL_RAD, LOOKAHEAD_S, ContactView, Motion, Task, TickInput

PROBE_OVERSHOOT_M = 0.002     # phase-1 target lies beyond the probe distance so the TCP never stops there
TOOL_TURN_RAMP_S = 0.5        # rotate: the tool's turning with the arc fades in over this long
# Arc radius correction per newton of radial grasp force, m/(N s). It integrates the force, so
# against a grasp of radial stiffness k the loop's bandwidth is ARC_ADMITTANCE_M_NS * k, behind a
# delay of a control tick, the arm's command latency and the planner's response (50-80 ms on a
# Franka). It is set for a soft grasp (about 5 kN/m: 5/s, well damped behind that delay; a
# stiffer gain rings at the arc's end), and still follows a radius that drifts 0.3 mm/s (an
# estimate 2 mm off at 2 cm/s) within 0.1 mm. docs/franka.md has the measurements.
ARC_ADMITTANCE_M_NS = 0.001
ARC_RADIAL_MAX_M = 0.02       # the radius correction stays within this


class TwoPhaseTask(Task):
    """Algorithm 2 of the paper.

    Phase 1 (`probe`): open-loop straight motion along `direction` for
    `probe_distance` while the contact estimator converges. Phase 2 (`arc`):
    each tick, a target on the circle about the current hinge estimate,
    through the TCP's start position, `LOOKAHEAD_S` ahead at `speed`, with the
    tangential target velocity, until the rotation reaches `angle_rad`. The
    circle's radius follows the grasp force along the lever arm (a radial
    admittance, not in the paper), so an estimate a little off does not drag
    the object's base. With strategy `straight` phase 2 is instead a straight pull of the same
    length as the arc (the paper's failure case).

    Unlike the paper's pseudo-code, which computes the phase-1 direction from
    the *true* contact point, the direction here comes from the command: the
    controller does not know the geometry.
    """

    class Phase(enum.StrEnum):
        PROBE = "probe"
        ARC = "arc"
        STRAIGHT = "straight"

    kind = "rotate"
    absorbed_phases = (Phase.ARC,)

    def __init__(self, task_id: str, angle_rad: float, speed: float, probe_distance: float,
                 direction: np.ndarray, strategy: str = "arc", turn_tool: bool = False):
        if strategy not in ("arc", "straight"):
            raise ValueError("strategy: expected 'arc' or 'straight'")
        super().__init__(task_id, direction, speed)
        self.angle_rad = angle_rad
        # Phase 1 stays short (the paper's 5 mm): a straight probe changes the lever arm as the
        # object turns, which biases every estimator in proportion to the angle.
        self.probe_distance = probe_distance
        self.strategy = strategy
        self._axis_sign = 1.0
        self._straight_len = 0.0
        self._angle = 0.0
        self._radius = 0.0
        self.turn_tool = turn_tool
        self._turn = 0.0                # how far the tool has turned on the arc, rad
        self._turn_t0 = None            # when it began to turn
        self._phi_last = 0.0            # planned arc angle and time of the previous tick
        self._t_last = None
        self._f0 = None                 # TCP force at the start (the robot's bias and the grasp's preload)
        self._radial = 0.0              # arc radius correction from the grasp force, m
        self._end_p: np.ndarray | None = None   # the arc's end, kept once the look-ahead has reached it
        self._t_radial = None

    def _started(self, inp: TickInput) -> None:
        # The tool holds the object from the start (the paper's Algorithm 2 begins grasped): the probe
        # starts the contact episode itself, as it starts the motion, rather than wait for a trigger
        # that a smooth start from rest gives no impact to fire on.
        self.episode += 1
        self.commanded_onset = True
        self._enter(self.Phase.PROBE, inp.t)

    def _tick(self, inp: TickInput) -> None:
        if self._f0 is None and inp.contact_force is not None:
            self._f0 = np.asarray(inp.contact_force, dtype=float).copy()

    def _step_probe(self, inp: TickInput) -> Motion | None:
        s = float(np.dot(inp.p - self.p_start, self.direction))
        self.status.progress = 0.1 * min(max(s / self.probe_distance, 0.0), 1.0)
        if s >= self.probe_distance:
            c = inp.contact
            if not c.tracking or c.p is None:
                self._fail("no contact estimate after probing (the estimator has not started)")
                return None
            if c.axis is None:
                self._fail(f"no axis yet: the fingertip saw no rotation over the {self.probe_distance * 1e3:.0f} mm "
                           "probe (is the tool holding the object, and does it turn?)")
                return None
            self._axis_sign = self._orient_axis(c)
            self.angle_rad = self._phase2_angle(c)
            if self.strategy == "straight":
                self._straight_len = self.angle_rad * self._radius_about(c.p, c.axis)
                self._enter(self.Phase.STRAIGHT, inp.t)
                return self._step_straight(inp)
            self._enter(self.Phase.ARC, inp.t)
            return self._step_arc(inp)
        if self._timed_out(inp.t, self.probe_distance / self.speed):
            self._fail("probing did not cover probe_distance in time")
            return None
        target = self.p_start + (self.probe_distance + PROBE_OVERSHOOT_M) * self.direction
        return Motion(target, self.speed * self.direction, self.R_hold)

    def _phase2_angle(self, c: ContactView) -> float:
        """Rotation to perform in phase 2, rad, fixed when phase 1 ends."""
        return self.angle_rad

    def _orient_axis(self, c: ContactView) -> float:
        """Sign making the rotation about the axis start along the probing direction."""
        r = self.p_start - c.p
        return 1.0 if float(np.dot(np.cross(c.axis, r), self.direction)) >= 0 else -1.0

    def _radius_about(self, p_c: np.ndarray, axis: np.ndarray) -> float:
        r = self.p_start - p_c
        return float(np.linalg.norm(r - np.dot(r, axis) * axis))

    def _step_arc(self, inp: TickInput) -> Motion | None:
        c = inp.contact
        a = self._axis_sign * unit(c.axis, "axis")
        r0 = self.p_start - c.p
        along = float(np.dot(r0, a))
        r0_perp = r0 - along * a
        rho = float(np.linalg.norm(r0_perp))
        if rho < 0.01:
            self._fail(f"hinge estimate {rho * 1000:.1f} mm from the TCP: too close to follow an arc")
            return None
        phi = signed_angle(r0, inp.p - c.p, a)
        self._angle, self._radius = phi, rho
        # The look-ahead advances from the *planned* position: the arm runs a little ahead of or
        # behind the plan, and a target placed from the measured TCP would run away (or stall),
        # making the planner cut across the arc.
        p_ref = inp.p_ref
        phi_plan = signed_angle(r0, p_ref - c.p, a)
        self.status.progress = 0.1 + 0.9 * min(max(phi / self.angle_rad, 0.0), 1.0)
        remaining = self.angle_rad - phi
        if (self._end_p is not None or remaining <= ANGLE_TOL_RAD) and inp.planner_at_rest:
            self._finish(c)
            return None
        if self._timed_out(inp.t, self.angle_rad * rho / self.speed):
            self._fail("arc following did not reach the angle in time")
            return None
        lookahead = self.speed * LOOKAHEAD_S / rho
        phi_t = min(phi_plan + lookahead, self.angle_rad)
        Rot = rotvec_to_matrix(a * phi_t)
        target = c.p + Rot @ r0 + self._radius_correction(inp, c.p, a) * (Rot @ r0_perp) / rho
        tangent = np.cross(a, Rot @ r0_perp) / rho
        v = self.speed * tangent if phi_t < self.angle_rad else np.zeros(3)
        R, w = self._tool_on_arc(inp.t, phi_plan, a)
        if phi_t >= self.angle_rad:
            # The look-ahead has reached the arc's end: that end is kept from now on (the tool
            # still turns with the plan). Re-placed each tick about the newest estimate and the
            # admittance's radius it would move by micrometres, the planner would never come to
            # rest, and on a soft grasp the arm would creep and the handle spring, which the
            # estimator's divergence stop takes for a failure. The task ends once the planner is at
            # rest there.
            if self._end_p is None:
                self._end_p = target
            target = self._end_p
        # Ruckig's limits are per axis: without a duration it would race a look-ahead target
        # with every axis at the limit (up to sqrt(2) x speed on a tilted arc).
        return Motion(target, v, R, min_duration_s=(phi_t - phi_plan) * rho / self.speed, w=w)

    def _radius_correction(self, inp: TickInput, p_c: np.ndarray, a: np.ndarray) -> float:
        """Radial admittance: the handle's true circle is where the grasp force has no radial part.
        Off it, the soft grasp stretches (the force pulls the TCP towards the hinge) or compresses;
        the arc's radius moves with that force, so an estimate whose radius or centre is a little
        off does not drag the object's base. The estimator distrusts the velocity along the lever
        arm on the arc, so the correction does not feed back into the estimate."""
        if inp.contact_force is None or self._f0 is None:
            return self._radial
        dt = 0.0 if self._t_radial is None else inp.t - self._t_radial
        self._t_radial = inp.t
        r = inp.p - p_c
        r = r - float(r @ a) * a
        n = float(np.linalg.norm(r))
        if n > 1e-6 and dt > 0:
            f_r = float((np.asarray(inp.contact_force, dtype=float) - self._f0) @ (r / n))
            self._radial = min(max(self._radial + ARC_ADMITTANCE_M_NS * f_r * dt, -ARC_RADIAL_MAX_M),
                               ARC_RADIAL_MAX_M)
        return self._radial

    def _tool_on_arc(self, t: float, phi_plan: float, a: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The tool's orientation on the arc: held, or (turn_tool) turned with the arc about the
        estimated axis, with its rate as feed-forward. The turning rate fades in over
        TOOL_TURN_RAMP_S (smoothstep) to the planned arc rate: a gripper rate that jumps would be
        seen late by 65 Hz proprioception, from which the estimator takes the gripper's rate. The
        tool then trails the handle by a constant angle (half the ramp times the arc rate: 1.1 to
        2.9 deg over radii 25 to 10 cm at 2 cm/s), well inside the fingertips' stick range."""
        if not self.turn_tool:
            return self.R_hold, None
        if self._turn_t0 is None:
            self._turn_t0, self._phi_last = t, phi_plan
        x = min((t - self._turn_t0) / TOOL_TURN_RAMP_S, 1.0)
        fade = x * x * (3.0 - 2.0 * x)
        step = fade * (phi_plan - self._phi_last)
        dt = t - self._t_last if self._t_last is not None else 0.0
        self._turn += step
        self._phi_last, self._t_last = phi_plan, t
        return rotvec_to_matrix(a * self._turn) @ self.R_hold, a * (step / dt if dt > 0 else 0.0)

    def _step_straight(self, inp: TickInput) -> Motion | None:
        s = float(np.dot(inp.p - self.p_start, self.direction))
        self.status.progress = 0.1 + 0.9 * min(max(s / max(self._straight_len, 1e-9), 0.0), 1.0)
        if s >= self._straight_len - 1e-4 and inp.planner_at_rest:
            c = inp.contact
            if c.p is not None:
                self._angle = signed_angle(self.p_start - c.p, inp.p - c.p, self._axis_sign * c.axis)
                self._radius = self._radius_about(c.p, c.axis)
            self._finish(c)
            return None
        if self._timed_out(inp.t, self._straight_len / self.speed):
            self._fail("straight pull did not finish in time")
            return None
        return Motion(self.p_start + self._straight_len * self.direction, np.zeros(3), self.R_hold)

    def _finish(self, c: ContactView) -> None:
        self._done({
            "hinge": {"p": c.p.tolist(), "std": c.std.tolist(), "axis": (self._axis_sign * c.axis).tolist()},
            "p": c.p.tolist(),
            "std": c.std.tolist(),
            "angle_deg": math.degrees(self._angle),
            "radius": self._radius,
            "strategy": self.strategy,
        })

    STEPS = {Phase.PROBE: _step_probe, Phase.ARC: _step_arc, Phase.STRAIGHT: _step_straight}


class RotateTask(TwoPhaseTask):
    """Opens an articulated object; on the arc the tool turns with it (the grasp stays in stick)."""

    kind = "rotate"
    # a probe across the handle instead of along its tangent: the gyro's twist then fits no hinge (a second
    # rotate with the first's direction, the handle having turned since, failed 3 times in 3 this way)
    stop_hints = {"divergence": "is --direction along the handle's tangent at the grasp? After a rotate the "
                                "tangent has turned with the handle: give the new one (a rotate without "
                                "--direction takes it from the last rotate's hinge while the TCP is on its circle)"}

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("turn_tool", True)
        super().__init__(*args, **kwargs)


class ProbeTask(TwoPhaseTask):
    """Probe (Algorithm 2): phase 1 for `distance`, then arc-follow the same arc length; result is the contact."""

    kind = "probe"

    def __init__(self, task_id: str, speed: float, distance: float, direction: np.ndarray):
        super().__init__(task_id, angle_rad=0.0, speed=speed, probe_distance=distance, direction=direction)
        self._arc_len = distance

    def _phase2_angle(self, c: ContactView) -> float:
        return self._arc_len / max(self._radius_about(c.p, c.axis), 0.01)

    def _finish(self, c: ContactView) -> None:
        super()._finish(c)
        self.status.result = {"p": c.p.tolist(), "std": c.std.tolist(),
                              "axis": (self._axis_sign * c.axis).tolist(),
                              "angle_deg": math.degrees(self._angle), "radius": self._radius}
