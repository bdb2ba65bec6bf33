"""`home`: a slow joint-space move to `robot.q_home`, jerk-limited (Ruckig over the joints), paced so
that no joint exceeds the asked joint speed and the TCP stays under the TCP speed limit, and checked
against the workspace box along its whole path before it starts.

It is the one task that commands joints rather than a Cartesian plan: its Motion carries the joint
velocities (`qd`), the plan's velocity plus feedback on the measured joints against the plan at the
state's time. The onset trigger is never armed (moving home is not probing), and a joint that lags
its plan by more than JOINT_TRACKING_RAD fails the task (the arm is held, as on any failure).
"""
from __future__ import annotations

import enum
import math

import numpy as np
import ruckig

from tecdard.control.tasks import Motion, Task, TickInput

JOINT_ACCEL_RAD_S2 = 0.5       # the move's joint acceleration bound (a slow, soft start and end)
JOINT_JERK_RAD_S3 = 2.0
JOINT_GAIN_PER_S = 2.0         # feedback on the joint error against the plan, 1/s
JOINT_TRACKING_RAD = 0.05      # a joint further than this from its plan fails the task (~3 deg)
PATH_CHECK_S = 0.02            # the path is checked against the workspace box every this often
HOME_TOL_RAD = 0.002           # already home: every joint within this
ARRIVE_TIMEOUT_S = 5.0         # after the plan's end, the arm has this long to settle within HOME_TOL_RAD x 5


class HomeRefused(ValueError):
    """The move cannot be made from here (leaves the workspace box, or no plan)."""


def plan_home(q_from: np.ndarray, q_home: np.ndarray, joint_speed: float, tcp_speed_max: float, fk,
              workspace_min, workspace_max) -> ruckig.Trajectory:
    """The joint trajectory from `q_from` to `q_home`: every joint within `joint_speed` (rad/s),
    the TCP (fk(q) -> position, m) within `tcp_speed_max` (m/s), and inside the workspace box all
    along; HomeRefused otherwise."""
    n = len(q_home)
    inp = ruckig.InputParameter(n)
    inp.current_position = [float(x) for x in q_from]
    inp.target_position = [float(x) for x in q_home]
    inp.max_velocity = [float(joint_speed)] * n
    inp.max_acceleration = [JOINT_ACCEL_RAD_S2] * n
    inp.max_jerk = [JOINT_JERK_RAD_S3] * n
    traj = ruckig.Trajectory(n)
    for _ in range(3):                      # stretch the move until the TCP is slow enough
        result = ruckig.Ruckig(n).calculate(inp, traj)
        if result not in (ruckig.Result.Working, ruckig.Result.Finished):
            raise HomeRefused(f"home: no joint plan ({result})")
        ts = np.arange(0.0, traj.duration + PATH_CHECK_S, PATH_CHECK_S)
        p = np.array([fk(np.array(traj.at_time(min(t, traj.duration))[0])) for t in ts])
        lo, hi = np.asarray(workspace_min), np.asarray(workspace_max)
        outside = np.any((p < lo) | (p > hi), axis=1)
        if np.any(outside):
            where = p[int(np.argmax(outside))]
            raise HomeRefused(f"home: the path to q_home leaves the workspace box at "
                              f"{np.round(where * 1e3, 1).tolist()} mm; move the arm closer to home first")
        speed = float(np.max(np.linalg.norm(np.diff(p, axis=0), axis=1)) / PATH_CHECK_S) if len(p) > 1 else 0.0
        if speed <= tcp_speed_max:
            return traj
        inp.minimum_duration = traj.duration * speed / tcp_speed_max * 1.05
    return traj


class HomeTask(Task):
    """Move the joints to q_home along a planned trajectory, then hold (see the module's docstring).
    `on_start` and `on_home` (optional) are called on the first tick and once home: the simulator's
    world is let go and rebuilt there (`home --reset-world`)."""

    class Phase(enum.StrEnum):
        MOVE = "move"
        SETTLE = "settle"

    kind = "home"
    trigger_phase = "never"          # no phase of this task arms the onset trigger

    def __init__(self, task_id: str, q_from: np.ndarray, q_home: np.ndarray, trajectory: ruckig.Trajectory,
                 joint_speed: float, on_start=None, on_home=None):
        super().__init__(task_id, np.array([0.0, 0.0, 1.0]), 1e-3)
        self.q_from, self.q_home = np.asarray(q_from, float), np.asarray(q_home, float)
        self.traj = trajectory
        self.joint_speed = joint_speed
        self.on_start, self.on_home = on_start, on_home
        self._t0 = None

    def _started(self, inp: TickInput) -> None:
        self._enter(self.Phase.MOVE, inp.t)
        self._t0 = inp.t
        if self.on_start is not None:
            self.on_start()

    def _plan_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        q, qd, _ = self.traj.at_time(min(max(t - self._t0, 0.0), self.traj.duration))
        return np.array(q), np.array(qd)

    def _step_move(self, inp: TickInput) -> Motion | None:
        if inp.q is None:
            self._fail("home: no joint state")
            return None
        t_state = inp.t if inp.q_t is None else inp.q_t
        q_ref, qd_ref = self._plan_at(t_state)
        err = q_ref - inp.q
        worst = int(np.argmax(np.abs(err)))
        if abs(err[worst]) > JOINT_TRACKING_RAD:
            self._fail(f"home: joint {worst + 1} is {math.degrees(abs(err[worst])):.1f} deg from its plan "
                       f"(limit {math.degrees(JOINT_TRACKING_RAD):.1f} deg): blocked, or the arm is not following")
            return None
        _, qd_now = self._plan_at(inp.t)
        qd = qd_now + JOINT_GAIN_PER_S * err
        cap = 1.2 * self.joint_speed                       # feedback never drives a joint much past the asked speed
        qd = np.clip(qd, -cap, cap)
        elapsed = inp.t - self._t0
        self.status.progress = min(elapsed / max(self.traj.duration, 1e-6), 1.0)
        if elapsed >= self.traj.duration:
            self._enter(self.Phase.SETTLE, inp.t)
        return Motion(inp.p, np.zeros(3), inp.R, qd=qd)

    def _step_settle(self, inp: TickInput) -> Motion | None:
        err = self.q_home - inp.q
        if float(np.max(np.abs(err))) <= HOME_TOL_RAD:
            if self.on_home is not None:
                self.on_home()
            self._done({"q": inp.q.tolist(), "p": inp.p.tolist(),
                        "max_joint_error_deg": math.degrees(float(np.max(np.abs(err))))})
            return None
        if inp.t - self._phase_t0 > ARRIVE_TIMEOUT_S:
            self._fail(f"home: the arm stayed {math.degrees(float(np.max(np.abs(err)))):.2f} deg from q_home")
            return None
        qd = np.clip(JOINT_GAIN_PER_S * err, -self.joint_speed, self.joint_speed)
        return Motion(inp.p, np.zeros(3), inp.R, qd=qd)

    STEPS = {Phase.MOVE: _step_move, Phase.SETTLE: _step_settle}
