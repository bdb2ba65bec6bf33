"""Task state machines stepped by the 20 ms control tick: what every task shares, and the simple ones
(approach, point). The paper's Algorithm 2 (rotate, probe) is control.rotate, the tactile map
control.mapping.

Each task names its phases in an enum (`Phase`) and steps the phase it is in with the method
`STEPS` gives for it: one dispatch for every task (Task.step).
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from tecdard.control.geometry import unit

LOOKAHEAD_S = 0.25            # arc target placed this far ahead along the arc, at the commanded speed
ANGLE_TOL_RAD = math.radians(0.2)
PHASE_TIMEOUT_FACTOR = 4.0    # a phase may take this many times its nominal duration (+ slack)
PHASE_TIMEOUT_SLACK_S = 2.0


@dataclass
class ContactView:
    """What a task may know of the contact: the estimator's latest output."""
    tracking: bool
    p: np.ndarray | None = None       # contact / hinge point, world, m
    std: np.ndarray | None = None     # one-sigma, m
    axis: np.ndarray | None = None    # rotation axis estimate, world unit
    onset_t: float | None = None
    in_plane_std: float = float("inf")  # the estimator's statistical one-sigma in the plane of rotation, m
    angle_rad: float = 0.0              # rotation of the object since onset (gyro), rad
    onset_p_tcp: np.ndarray | None = None   # the TCP at the onset sample (proprioception, causal), world, m


@dataclass
class TickInput:
    t: float                  # s, monotonic
    p: np.ndarray             # measured TCP position, world, m
    R: np.ndarray             # measured TCP orientation, world <- TCP
    contact: ContactView
    planner_at_rest: bool
    p_plan: np.ndarray | None = None   # where the planner has the TCP now (None: use p)
    contact_force: np.ndarray | None = None    # force of the world on the TCP, world, N (None: not measured)
    q: np.ndarray | None = None        # measured joint positions, rad (joint-space tasks: home)
    q_t: float | None = None           # when `q` was measured, s, monotonic

    @property
    def p_ref(self) -> np.ndarray:
        """Where the planner has the TCP now (the measured position when there is no plan)."""
        return self.p if self.p_plan is None else self.p_plan


@dataclass
class Motion:
    """The planner target for this tick and the orientation to hold."""
    p: np.ndarray
    v: np.ndarray
    R: np.ndarray
    min_duration_s: float | None = None   # reach the target no sooner than this (paces look-ahead targets)
    w: np.ndarray | None = None           # angular velocity feed-forward of the orientation target, world, rad/s
    max_speed: float | None = None        # TCP speed cap for this motion, m/s (None: the task's speed)
    qd: np.ndarray | None = None          # joint velocities instead of a Cartesian target, rad/s (home)


class TaskState(enum.StrEnum):
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


@dataclass
class TaskStatus:
    state: TaskState = TaskState.RUNNING
    phase: str = "start"                # the task's Phase (a str); "start" until its first tick
    progress: float = 0.0
    result: dict = field(default_factory=dict)
    error: str = ""


class Task:
    """What every task shares: its id, direction and speed, its status, and the TCP pose latched
    on its first tick (the start position, and the orientation it holds).

    `trigger_phase`: None, the onset trigger is armed for the whole task; or the phase in which
    it is armed, and then only while the arm moves steadily at `speed` (its own acceleration
    would look like an impact). `episode` counts contact episodes: the controller starts a
    fresh one (the estimator released, older onsets ignored) whenever it changes, and with
    `commanded_onset` set it starts the estimator at once instead of waiting for the trigger.
    In `touching_phases` the gyro bias is held: the tool's rotations there are not bias. In
    `absorbed_phases` the estimator distrusts the TCP velocity along the lever arm (arc following
    about an estimate, pushing on after an impact, tilting a tool out).
    """

    kind = "task"
    Phase: type = enum.StrEnum          # the task's phases (each task's own enum)
    STEPS: dict = {}                    # Phase -> the method that steps it
    trigger_phase: str | None = None
    touching_phases: tuple = ()        # phases where the tool touches outside a contact episode
    absorbed_phases: tuple = ()        # phases where the grasp absorbs the TCP's motion along the lever arm
    reactions: tuple = ()              # the task's own safety checks (control.safety.Reaction), after the generic ones
    stop_hints: dict = {}              # protective stop cause -> the likely cause in this task, added to its message

    def __init__(self, task_id: str, direction: np.ndarray, speed: float):
        self.id = task_id
        self.direction = unit(direction, "direction")
        self.speed = speed
        self.status = TaskStatus()
        self.p_start: np.ndarray | None = None
        self.R_hold: np.ndarray | None = None
        self.episode = 0
        self.commanded_onset = False
        self._phase_t0 = 0.0

    def step(self, inp: TickInput) -> Motion | None:
        """Advance the state machine one tick: the step of the phase it is in (STEPS). Returns the
        motion target, or None to brake or hold."""
        if not self._running(inp):
            return None
        self._tick(inp)
        return self.STEPS[self.status.phase](self, inp)

    def _running(self, inp: TickInput) -> bool:
        """False once done or failed; on the first tick, latches the start pose."""
        if self.status.state is not TaskState.RUNNING:
            return False
        if self.p_start is None:
            self.p_start = inp.p.copy()
            self.R_hold = inp.R.copy()
            self._started(inp)
        return True

    def _started(self, inp: TickInput) -> None:
        """Called once, on the first tick: enter the first phase."""

    def _tick(self, inp: TickInput) -> None:
        """Called every tick before the phase's step."""

    def _enter(self, phase: str, t: float) -> None:
        self.status.phase = phase
        self._phase_t0 = t

    def _timed_out(self, t: float, nominal_s: float) -> bool:
        """The current phase has taken far longer than its nominal duration."""
        return t - self._phase_t0 > PHASE_TIMEOUT_FACTOR * nominal_s + PHASE_TIMEOUT_SLACK_S

    def _done(self, result: dict) -> None:
        st = self.status
        st.state, st.progress, st.result = TaskState.DONE, 1.0, result

    def _fail(self, message: str) -> None:
        self.status.state = TaskState.FAILED
        self.status.error = message

    def ended_early(self) -> dict:
        """The task was stopped, cancelled or failed: hand off whatever it still has to write (a map's
        points probed so far) and return the fields its `task_failed` event adds ({} by default)."""
        return {}


class ApproachTask(Task):
    """Move along `direction` at `speed` until the trigger fires, keep tracking the contact during
    the ongoing motion, and finish once the object has turned `stop_angle_rad` (the paper's
    ongoing-movement case). Never travels beyond `max_distance`: without a contact by then the
    task fails."""

    class Phase(enum.StrEnum):
        APPROACH = "approach"
        CONTACT = "contact"

    kind = "approach"
    trigger_phase = Phase.APPROACH
    absorbed_phases = (Phase.CONTACT,)

    def __init__(self, task_id: str, direction: np.ndarray, speed: float, max_distance: float,
                 stop_angle_rad: float):
        super().__init__(task_id, direction, speed)
        self.max_distance = max_distance
        self.stop_angle_rad = stop_angle_rad

    def _started(self, inp: TickInput) -> None:
        self._enter(self.Phase.APPROACH, inp.t)

    def _step(self, inp: TickInput) -> Motion | None:
        """Both phases: along the direction until the contact shows, then on until it has turned enough."""
        st = self.status
        s = float(np.dot(inp.p - self.p_start, self.direction))
        # how far the plan has gone: the arm trails it by a hair at the end of a paced move
        s_plan = float(np.dot(inp.p_ref - self.p_start, self.direction))
        c = inp.contact
        if c.tracking and c.p is not None:
            st.phase = self.Phase.CONTACT
            st.progress = 0.5 + 0.5 * min(c.angle_rad / self.stop_angle_rad, 1.0)
            if c.angle_rad >= self.stop_angle_rad or s_plan >= self.max_distance - 1e-5:
                self._done({"p": c.p.tolist(), "std": c.std.tolist(),
                            "axis": None if c.axis is None else c.axis.tolist(),
                            "angle_deg": math.degrees(c.angle_rad), "travel": s})
                return None
        else:
            st.progress = 0.5 * min(max(s / self.max_distance, 0.0), 1.0)
            if s_plan >= self.max_distance - 1e-5:
                self._fail(f"no contact within max_distance {self.max_distance:g} m")
                return None
        target = self.p_start + self.max_distance * self.direction
        # constant speed all the way: the target is paced (Ruckig would otherwise race it)
        p_ref = inp.p_ref
        remaining = max(float(np.dot(target - p_ref, self.direction)), 0.0)
        return Motion(target, np.zeros(3), self.R_hold, min_duration_s=remaining / self.speed)

    STEPS = {Phase.APPROACH: _step, Phase.CONTACT: _step}


POINT_RESOLVED_STD_M = 0.02   # a point result needs every axis known this well


class PointTask(Task):
    """Circular probing of a point contact (the paper's pen): a tool touching a point is tilted
    outward by `radius` and its TCP then circles `turns` times at constant height about the
    vertical through the start (the paper's in-plane circle). The tool sweeps a cone about its
    tip, which turns the rotation axis through every horizontal direction and makes all three
    coordinates of the tip observable.

    On the circle the distance from the TCP to the tip of an upright tool stays constant, so the
    estimator trusts the TCP velocity along the tool there: that component is what resolves the
    tip's horizontal coordinates. While tilting out it does not (the grasp stretches a little).
    A tool tilted in the grasp breaks the cone: see docs/zenoh-api.md.
    """

    class Phase(enum.StrEnum):
        OUT = "out"
        CIRCLE = "circle"

    kind = "point"
    absorbed_phases = (Phase.OUT,)

    def __init__(self, task_id: str, radius: float, speed: float, turns: float):
        super().__init__(task_id, np.array([1.0, 0.0, 0.0]), speed)
        self.radius = radius
        self.turns = turns
        self.e2 = np.array([0.0, 1.0, 0.0])
        self._psi = 0.0                 # angle travelled on the circle, rad (unwrapped)
        self._psi_plan = 0.0

    def _started(self, inp: TickInput) -> None:
        # the tool touches its point from the start: the tilt starts the contact episode itself
        self.episode += 1
        self.commanded_onset = True
        self._enter(self.Phase.OUT, inp.t)

    def _on_circle(self, psi: float) -> np.ndarray:
        """The circle point at angle psi, at the start height."""
        return self.p_start + self.radius * (math.cos(psi) * self.direction + math.sin(psi) * self.e2)

    def _angle_of(self, p: np.ndarray) -> float:
        d = p - self.p_start
        return math.atan2(float(d @ self.e2), float(d @ self.direction))

    def _step_out(self, inp: TickInput) -> Motion | None:
        """Tilt the tool out: the TCP to the circle's start, at the start height."""
        st, p_ref = self.status, inp.p_ref
        s_plan = float(np.dot(p_ref - self.p_start, self.direction))
        st.progress = 0.1 * min(max(s_plan / self.radius, 0.0), 1.0)
        if s_plan >= self.radius - 1e-4:
            self._enter(self.Phase.CIRCLE, inp.t)
            self._psi = self._psi_plan = 0.0
            return self._step_circle(inp)
        if self._timed_out(inp.t, self.radius / self.speed):
            self._fail("tilting out to the circle did not finish in time")
            return None
        target = self._on_circle(0.0)
        remaining = max(float(np.linalg.norm(target - p_ref)), 0.0)
        return Motion(target, np.zeros(3), self.R_hold, min_duration_s=remaining / self.speed)

    def _step_circle(self, inp: TickInput) -> Motion | None:
        """Circle the TCP `turns` times; the angle travelled unwrapped, measured and planned."""
        st, c, p_ref = self.status, inp.contact, inp.p_ref
        total = 2.0 * math.pi * self.turns
        self._psi += _wrap(self._angle_of(inp.p) - self._psi)
        self._psi_plan += _wrap(self._angle_of(p_ref) - self._psi_plan)
        st.progress = 0.1 + 0.9 * min(max(self._psi / total, 0.0), 1.0)
        if self._psi_plan >= total - ANGLE_TOL_RAD and inp.planner_at_rest:
            self._finish(c)
            return None
        if self._timed_out(inp.t, total * self.radius / self.speed):
            self._fail("circular probing did not complete in time")
            return None
        psi_t = min(self._psi_plan + self.speed * LOOKAHEAD_S / self.radius, total)
        target = self._on_circle(psi_t)
        tangent = -math.sin(psi_t) * self.direction + math.cos(psi_t) * self.e2
        v = self.speed * tangent if psi_t < total else np.zeros(3)
        return Motion(target, v, self.R_hold, min_duration_s=(psi_t - self._psi_plan) * self.radius / self.speed)

    def _finish(self, c: ContactView) -> None:
        st = self.status
        if not c.tracking or c.p is None:
            self._fail("no contact detected during circular probing")
            return
        worst = float(np.max(c.std))
        if worst > POINT_RESOLVED_STD_M:
            self._fail(f"point contact not resolved: one-sigma {worst * 1e3:.0f} mm on some axis "
                       f"(a line contact, or slipping)")
            return
        self._done({"p": c.p.tolist(), "std": c.std.tolist(), "turns": self._psi / (2.0 * math.pi),
                    "lever_arm": float(np.linalg.norm(self.p_start - c.p))})

    STEPS = {Phase.OUT: _step_out, Phase.CIRCLE: _step_circle}


def _wrap(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi
