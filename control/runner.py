"""The control loop's task lifecycle, without threads: the mode, the running task, the Cartesian plan,
and what the estimator is told (an EstimatorDirective). tecdard/control_thread.py drives it once a tick."""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from tecdard.control import safety
from tecdard.control.modes import Event, Mode, transition
from tecdard.control.pipeline import EstimatorDirective
from tecdard.control.planner import CartesianPlanner, PlannerError
from tecdard.control.tasks import ContactView, Task, TaskState, TickInput

REST_SPEED_M_S = 1e-3         # the TCP counts as stopped below this speed
# The onset trigger arms once the plan has moved at constant speed this long: the arm follows the plan
# with a lag, and its own acceleration at the start of a descent must not read as an impact.
TRIGGER_SETTLE_S = 0.1
# A contact with no task ends once the arm and the fingertip rest (TaskRunner.end_idle_episode): the TCP slower
# than REST_SPEED_M_S, and the object turning slower than REST_TURN_RAD_S since the rest began (its angle is
# the gyro integrated less a bias frozen at the onset: at rest on a board it crept 0.15 deg/s after a knock),
# or by less than REST_ANGLE_RAD in the rest's first moments.
REST_ANGLE_RAD = np.radians(0.2)
REST_TURN_RAD_S = np.radians(1.0)


class TaskRunner:
    """Runs one task at a time through its life: start, a step per tick (safety, the task's motion,
    the plan), and its end (done, failed, cancelled, stopped), braking to rest after it.

    `emit(kind, **fields)` takes its events (task_started, task_done, task_failed, protective_stop);
    `on_rest()` is called when a brake has brought the arm to rest. A task that ends early hands off
    what it still has to write itself (Task.ended_early: a map's points)."""

    def __init__(self, planner: CartesianPlanner, limits: safety.SafetyLimits, emit: Callable,
                 on_rest: Callable = lambda: None):
        self.planner = planner
        self.limits = limits
        self.emit, self.on_rest = emit, on_rest
        self.mode = Mode.IDLE
        self.task: Task | None = None
        self.directive = EstimatorDirective()
        self.R_hold: np.ndarray | None = None   # the orientation to hold, world <- TCP
        self.w_ff = np.zeros(3)                # angular velocity feed-forward of the orientation target
        self.task_t0 = 0.0                     # the task's episode began here: older onsets do not count
        self.saturated = 0                     # IMU samples clipped at full scale in the task's episodes
        self._speed_cap = None                 # the planner's current TCP speed cap, m/s
        self._steady_since = None              # when the plan last became steady in the trigger's phase
        self._last_est = None                  # the contact estimate seen on the previous tick
        self.qd_cmd: np.ndarray | None = None  # this tick's joint velocities from a joint-space task (home)
        self._rest: tuple[float, float] | None = None    # an idle contact's rest: (since, the angle then)
        self._now = 0.0                        # the last tick's time

    # -- commands ---------------------------------------------------------------------
    def busy(self) -> str | None:
        """What keeps a new task from starting (the running task's id, or a stop), or None."""
        if self.mode is Mode.IDLE:
            return None
        return self.task.id if self.task is not None else "a stop"

    def start(self, task: Task, now: float, p: np.ndarray, params: dict) -> None:
        """Start `task` from the measured TCP position `p` (the caller has checked `busy()`)."""
        self.task = task
        self.mode = transition(self.mode, Event.START)
        self._last_est = None
        self.saturated = 0
        self.task_t0 = now
        self.planner.reset(p, speed=task.speed)
        self._speed_cap = task.speed
        self._steady_since = None
        # a fresh contact episode for this task; with a trigger phase the trigger is armed once the
        # approach moves at constant speed (the arm's own acceleration at the start looks like an impact)
        self._direct(episode=self.directive.episode + 1, armed=task.trigger_phase is None, begin_t=None, since_t=now)
        self.emit("task_started", task=task.id, verb=task.kind, params=params)

    def cancel(self, task_id: str | None) -> bool:
        """End the running task (if `task_id` is None or names it); False when there is none such."""
        if self.task is None or (task_id is not None and task_id != self.task.id):
            return False
        self.end("failed", error="cancelled")
        return True

    def stop(self, reason: str) -> None:
        """Stop: end any task, and brake to rest."""
        self.end("failed", error=reason)
        self.mode = transition(self.mode, Event.STOP)

    def protective_stop(self, cause: safety.StopCause, halted_at: np.ndarray | None = None) -> None:
        """End the task and brake to rest. `halted_at`: the measured TCP where the robot's own
        controller has stopped the arm (its protective stop, a lost program): the plan stops there
        at once, because a brake that ran on would only send motion the controller refuses now, or
        leaves in its command registers to run when its program is started again."""
        if halted_at is not None:
            self.planner.reset(halted_at)
        if self.mode is not Mode.IDLE:
            self.emit("protective_stop", cause=cause.cause, message=cause.message, **cause.details)
            self.stop(f"protective stop: {cause.message}")

    def reset(self) -> None:
        """After a failed tick the caller has held the arm: the plan starts from where it is."""
        self.planner.reset(self.planner.position)
        self.mode = transition(self.mode, Event.RESET)
        self._direct(armed=True)

    # -- each tick ------------------------------------------------------------------------
    def check(self, contact_force, est) -> None:
        """The running task's safety: the contact force (world, N), the estimate's checks and the task's
        own reactions."""
        if self.mode is not Mode.BUSY:
            return
        if est is not None and (est.onset_t is None or est.onset_t < self.task_t0):
            est = None                                     # an earlier episode's
        cause = safety.check_task(safety.SafetyInput(contact_force, est, self._last_est), self.limits, self.task.reactions)
        if cause is not None:
            hint = self.task.stop_hints.get(cause.cause)
            self.protective_stop(cause if hint is None else dataclasses.replace(cause, message=f"{cause.message}; {hint}"))
        elif est is not None:
            self._last_est = est

    def step(self, now: float, p: np.ndarray, R: np.ndarray, est, contact_force, q: np.ndarray | None = None,
             q_t: float | None = None, v: np.ndarray | None = None) -> np.ndarray | None:
        """The commanded TCP position one tick ahead, or None: the arm is to be held (idle). A
        joint-space task leaves its joint velocities in `qd_cmd` instead (the plan then follows the
        measured TCP: `v` its velocity, so that a stop brakes from there)."""
        self.qd_cmd = None
        self._now = now
        if self.mode is Mode.BUSY:
            p_cmd = self._step_task(now, p, R, est, contact_force, q, q_t, v)
        elif self.mode.braking:
            p_cmd = self._brake_step()
        else:
            self.planner.reset(p)
            if self.R_hold is None:
                self.R_hold = R
        if self.mode is Mode.IDLE:
            self.w_ff = np.zeros(3)
            return None
        return p_cmd

    def _step_task(self, now: float, p: np.ndarray, R: np.ndarray, est, contact_force, q=None, q_t=None,
                   v=None) -> np.ndarray:
        task = self.task
        if est is not None and est.onset_t is not None and est.onset_t >= self.task_t0:
            self.saturated = max(self.saturated, est.saturated)
            view = ContactView(tracking=True, p=est.p, std=est.std, axis=est.axis, onset_t=est.onset_t,
                               onset_p_tcp=est.onset_p_tcp, in_plane_std=est.in_plane_std, angle_rad=est.angle_rad)
        else:
            view = ContactView(tracking=False)
        if task.trigger_phase is not None:
            self._direct(armed=self._trigger_armed(now, task))
        episode = task.episode
        motion = task.step(TickInput(now, p, R, view, self.planner.at_rest, self.planner.position, contact_force, q,
                                     q_t))
        if task.episode != episode:
            # the task starts a fresh contact episode: older onsets no longer count
            self.task_t0 = now
            self._last_est = None
            begin_t = now if task.commanded_onset else None
            task.commanded_onset = False
            self._direct(episode=self.directive.episode + 1, begin_t=begin_t, since_t=now,
                         armed=self.directive.armed if task.trigger_phase is None else False)
        # the task says where its TCP motion along the lever arm is absorbed by the grasp, and where
        # it touches outside an episode (the gyro's bias is then held)
        self._direct(arc_following=task.status.phase in task.absorbed_phases,
                     bias_held=task.status.phase in task.touching_phases)
        if motion is None:
            st = task.status
            if st.state is not TaskState.RUNNING:
                self.end(st.state, result=st.result, error=st.error)
            return self._brake_step()
        self.R_hold = motion.R
        self.w_ff = np.zeros(3) if motion.w is None else motion.w
        if motion.qd is not None:
            # a joint-space move (its path was checked against the workspace box when it was planned)
            self.planner.reset(p, v)
            self.qd_cmd = np.asarray(motion.qd, dtype=float)
            return p
        cap = task.speed if motion.max_speed is None else motion.max_speed
        if cap != self._speed_cap:
            self._speed_cap = cap
            self.planner.set_speed(cap)
        cause = safety.check_motion(motion.p, self.planner.position, p, self.limits)
        if cause is None:
            try:
                return self.planner.step(motion.p, motion.v, motion.min_duration_s)[0]
            except PlannerError as exc:
                cause = safety.StopCause("planner", str(exc))
        self.protective_stop(cause)
        return self._brake_step()

    def end_idle_episode(self, now: float, v: np.ndarray, est, rest_s: float, faulted: bool = False) -> None:
        """A contact with no task running (a bump of the idle arm, any contact of an observed one) is released
        once the arm and the fingertip have rested `rest_s`, or at once on a fault: the next contact is a new
        onset. (A task's episodes end with the task.) Only a task released them before; an idle daemon saw one
        onset of six impacts, an observer only its run's first contact."""
        if self.mode is not Mode.IDLE or est is None or est.onset_t is None or est.onset_t < self.task_t0:
            self._rest = None
            return
        moving = float(np.linalg.norm(v)) > REST_SPEED_M_S
        turned = abs(est.angle_rad - self._rest[1]) if self._rest is not None else 0.0
        if self._rest is None or moving or turned > max(REST_ANGLE_RAD, REST_TURN_RAD_S * (now - self._rest[0])):
            self._rest = None if moving else (now, est.angle_rad)
            if not faulted:
                return
        if faulted or now - self._rest[0] >= rest_s:
            self._rest = None
            self.task_t0 = now                 # this episode's estimates no longer count
            self._direct(episode=self.directive.episode + 1, armed=True, begin_t=None, since_t=now)
            self.emit("contact_released", onset_t=est.onset_t, reason="fault" if faulted else "rest",
                      p=[float(x) for x in est.p])

    def _trigger_armed(self, now: float, task: Task) -> bool:
        """Armed while the arm moves steadily, TRIGGER_SETTLE_S after the plan does: starting and
        braking are not impacts."""
        steady = task.status.phase == task.trigger_phase and self.planner.steady(task.speed)
        if not steady:
            self._steady_since = None
            return False
        if self._steady_since is None:
            self._steady_since = now
        return now - self._steady_since >= TRIGGER_SETTLE_S

    def _brake_step(self) -> np.ndarray:
        self.w_ff = np.zeros(3)
        try:
            p_cmd, v_cmd = self.planner.brake()
        except PlannerError:
            p_cmd, v_cmd = self.planner.position, np.zeros(3)
        if self.mode.braking and float(np.linalg.norm(v_cmd)) < REST_SPEED_M_S and self.planner.at_rest:
            self.mode = transition(self.mode, Event.AT_REST)
            self._direct(armed=True)          # at rest: the trigger may arm (once the fingertip has settled)
            self.on_rest()
        return p_cmd

    def end(self, outcome: str, result: dict | None = None, error: str = "") -> None:
        """End the running task (if any): its end event and a fresh episode for the estimator; a task
        that ends early writes what it still has (Task.ended_early)."""
        task = self.task
        if task is None:
            return
        self.task = None
        self.task_t0 = self._now               # the task's contact is over: no idle contact (end_idle_episode)
        self.mode = transition(self.mode, Event.END)
        # the trigger stays disarmed while the arm brakes: it arms at rest (_brake_step), and the
        # estimator waits for the fingertip to settle after that (OnsetDetector.rearm)
        self._direct(episode=self.directive.episode + 1, armed=False, arc_following=False, bias_held=False,
                     begin_t=None, since_t=None)
        if outcome == TaskState.DONE:
            result = dict(result or {})
            if self.saturated:
                # said in the result: those samples were left out, the estimate rests on the rest
                result["imu_saturated_samples"] = self.saturated
                result["warnings"] = [f"imu_saturated: {self.saturated} IMU samples clipped at full scale "
                                      "were left out of the estimate"]
            self.emit("task_done", task=task.id, verb=task.kind, result=result)
            return
        # nothing is lost: a map's points probed so far are fused and written all the same
        extra = task.ended_early()
        self.emit("task_failed", task=task.id, verb=task.kind, error=error, phase=task.status.phase, **extra)

    def _direct(self, **changes) -> None:
        self.directive = dataclasses.replace(self.directive, **changes)
