"""The 20 ms control thread: the loop that reads the arm, checks safety, steps the task, plans and servos.

The pieces it strings together are pure and live in control/: the mode table (control.modes), the
safety checks (control.safety), the Ruckig planner (control.planner), the servo (control.servo) and
the tasks (control.tasks, built by their verbs in tecdard/verbs/).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np

from control import safety
from control.geometry import matrix_to_quat
from control.modes import Event, Mode, transition
from control.planner import CartesianPlanner, PlannerError
from control.servo import PlanSample, joint_velocities
from control.tasks import ContactView, TickInput
from tecdard import commands as C
from tecdard import verbs
from tecdard.mapfiles import MapSettings, MapWriter
from tecdard.messages import Cancel, EstimatorDirective, LatestValue, Reply, StartTask, Stop
from tecdard.realtime import MAX_RT_PRIORITY, TickStats, apply_rt_priority
from tecdard.safejson import show_name

log = logging.getLogger("tecdar.control")

WORKSPACE_MAX_M = 5.0         # no arm reaches further from its base: a workspace corner beyond is a typo
COMMAND_QUEUE = 64            # task commands (StartTask, Cancel) waiting for the next tick
REST_SPEED_M_S = 1e-3         # the TCP counts as stopped below this speed
# The onset trigger arms once the plan has moved at constant speed this long: the arm follows the plan
# with a lag, and its own acceleration at the start of a descent must not read as an impact.
TRIGGER_SETTLE_S = 0.1


@dataclass
class ControlParams:
    tick_s: float = 0.02
    max_speed: float = 0.05
    max_accel: float = 0.5
    max_jerk: float = 5.0
    workspace_min: tuple = (-1.0, -1.0, 0.0)
    workspace_max: tuple = (1.0, 1.0, 1.5)
    imu_stale_s: float = 0.05
    max_tracking_error_m: float = 0.01
    max_force_n: float = 15.0          # protective stop above this force on the TCP
    max_rotation_deg: float = 95.0     # protective stop when the object has turned more than this
    max_nis_ratio: float = 10.0        # protective stop when the estimator's smoothed NIS ratio exceeds this
    max_contact_jump_m: float = 0.02   # protective stop when a converged estimate moves this far in one tick
    rt_priority: int | None = None     # SCHED_FIFO priority of the control thread, where the host allows it

    @classmethod
    def from_config(cls, section, max_speed: float) -> "ControlParams":
        d = cls()
        p = cls(
            tick_s=section.getfloat("tick_s", d.tick_s, minval=0.002, maxval=0.1),
            max_speed=max_speed,
            max_accel=section.getfloat("max_accel", d.max_accel, above=0.0, maxval=10.0),
            max_jerk=section.getfloat("max_jerk", d.max_jerk, above=0.0, maxval=500.0),
            workspace_min=tuple(section.getfloats("workspace_min", list(d.workspace_min), n=3, minval=-WORKSPACE_MAX_M,
                                                  maxval=WORKSPACE_MAX_M)),
            workspace_max=tuple(section.getfloats("workspace_max", list(d.workspace_max), n=3, minval=-WORKSPACE_MAX_M,
                                                  maxval=WORKSPACE_MAX_M)),
            imu_stale_s=section.getfloat("imu_stale_s", d.imu_stale_s, above=0.0, maxval=1.0),
            max_tracking_error_m=section.getfloat("max_tracking_error_m", d.max_tracking_error_m, above=0.0,
                                                  maxval=0.1),
            max_force_n=section.getfloat("max_force_n", d.max_force_n, above=0.0, maxval=200.0),
            max_rotation_deg=section.getfloat("max_rotation_deg", d.max_rotation_deg, above=0.0, maxval=360.0),
            max_nis_ratio=section.getfloat("max_nis_ratio", d.max_nis_ratio, above=1.0),
            max_contact_jump_m=section.getfloat("max_contact_jump_m", d.max_contact_jump_m, above=0.0, maxval=1.0),
            rt_priority=(section.getint("rt_priority", 0, minval=1, maxval=MAX_RT_PRIORITY)
                         if section.has("rt_priority") else None),
        )
        if any(lo >= hi for lo, hi in zip(p.workspace_min, p.workspace_max)):
            from tecdard.config import ConfigError
            raise ConfigError(f"{section.path}.workspace_min: must be below workspace_max on every axis")
        return p

    def safety_limits(self) -> safety.SafetyLimits:
        return safety.SafetyLimits(
            imu_stale_s=self.imu_stale_s, max_force_n=self.max_force_n, max_rotation_deg=self.max_rotation_deg,
            max_nis_ratio=self.max_nis_ratio, max_contact_jump_m=self.max_contact_jump_m,
            max_tracking_error_m=self.max_tracking_error_m, workspace_min=self.workspace_min,
            workspace_max=self.workspace_max)


class ControlThread:
    """Owns the mode, the task, the planner and the robot's commands.

    In: task commands through `submit` (StartTask, Cancel; a bounded queue read once per tick) and
    `request_stop` (a Stop from any thread: taken first on every tick, never behind anything).
    Out: a `Reply` per command on `replies` (unbounded: one per request), state and events on
    `outbox`, and what the estimator should do as one `EstimatorDirective` in `directive`.
    """

    def __init__(self, params: ControlParams, model, robot, ring, contact: LatestValue, directive: LatestValue,
                 outbox: queue.Queue, q_home: np.ndarray, robot_name: str, notifier=None,
                 map_settings: MapSettings | None = None, imu_saturated_since=None):
        self.params = params
        self.limits = params.safety_limits()
        self.model = model.clone()           # this thread's own pinocchio Data
        self.robot, self.ring, self.contact, self.outbox = robot, ring, contact, outbox
        self.directive = directive
        self._directive = directive.get() or EstimatorDirective()
        directive.set(self._directive)
        self.q_home, self.robot_name, self.notifier = q_home, robot_name, notifier
        self.map_settings = map_settings or MapSettings()
        self.maps = MapWriter(self.map_settings)
        self.imu_saturated_since = imu_saturated_since or (lambda: None)   # latest value of the estimator thread
        self.commands: queue.Queue = queue.Queue(maxsize=COMMAND_QUEUE)
        self.replies: queue.SimpleQueue = queue.SimpleQueue()
        self._stops: collections.deque = collections.deque()     # Stop requests, appended from any thread
        self.planner = CartesianPlanner(params.tick_s, params.max_speed, params.max_accel, params.max_jerk)
        self.stats = TickStats()
        self.mode = Mode.IDLE
        self.task = None
        self.faults: dict[str, str] = {}
        self._stop_waiters: list = []
        self._seq = 0
        self._R_hold = None
        self._w_ff = np.zeros(3)           # angular velocity feed-forward of the orientation target
        self._speed_cap = None             # the planner's current TCP speed cap, m/s
        self._task_t0 = 0.0                # the running task's episode began here: older onsets do not count
        self._task_saturated = 0           # IMU samples clipped at full scale in the task's episodes
        self._steady_since = None          # when the plan last became steady in the trigger's phase
        self._last_est = None              # the contact estimate seen on the previous tick
        self._t_boot = time.monotonic()
        self._late_s = 0.0                 # how late the current tick started, s
        self._stale_deferred = False
        self.first_tick = threading.Event()
        self.dropped = 0
        self._wd_interval = notifier.watchdog_interval_s() if notifier else None
        self._wd_last = 0.0

    # -- in (any thread) ----------------------------------------------------------
    def submit(self, msg: StartTask | Cancel) -> bool:
        """Queue a task command for the next tick; False when the queue is full."""
        try:
            self.commands.put_nowait(msg)
            return True
        except queue.Full:
            return False

    def request_stop(self, msg: Stop) -> None:
        """Stop whatever runs, at the next tick whatever else is queued; the Stop's request is
        answered once the arm is at rest."""
        self._stops.append(msg)

    def quiescent(self) -> bool:
        """No task, the arm at rest after any stop, and every map written (for an orderly shutdown)."""
        return self.mode is Mode.IDLE and self.maps.idle

    # -- the loop -------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        apply_rt_priority(self.params.rt_priority)
        tick_s = self.params.tick_s
        t_next = time.monotonic()
        failures = 0
        try:
            while not stop.is_set():
                t_next += tick_s
                t0 = time.monotonic()
                self._late_s = max(0.0, t0 - (t_next - tick_s))
                try:
                    self.tick(t0)
                    failures = 0
                except Exception as exc:      # a bug must not leave the arm moving or the daemon deaf
                    failures += 1
                    if failures == 1 or failures % 50 == 0:
                        log.exception("control tick failed (%d in a row)", failures)
                    self._internal_fault(exc)
                self.first_tick.set()
                self.stats.add(time.monotonic() - t0, self._late_s)
                delay = t_next - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    # Late: the next tick runs now, and the periods missed altogether are skipped
                    # (the plan follows wall time, so a burst of catch-up ticks would only cost CPU).
                    self.stats.overruns += 1
                    t_next += math.floor(-delay / tick_s) * tick_s
        finally:
            try:
                self.robot.hold()
            except Exception:
                log.exception("hold on exit failed")
            self.maps.shutdown()

    def tick(self, now: float) -> None:
        self.planner.advance(now)
        js = self.robot.read_state()
        oMtcp, twist = self.model.measured(js)
        p, R = oMtcp.translation.copy(), oMtcp.rotation.copy()
        est = self.contact.get()
        self._check_sensors(now)
        self._check_task(js, est)
        self._handle_commands(p)
        plan_now = (self.planner.position, self.planner.velocity)
        fallbacks = self.planner.fallbacks
        if self.mode is Mode.BUSY:
            p_cmd = self._step_task(now, p, R, est, js.tcp_force)
        elif self.mode.braking:
            p_cmd = self._brake_step()
        else:
            self.planner.reset(p)
            if self._R_hold is None:
                self._R_hold = R
        if self.planner.fallbacks != fallbacks:     # a task's step or a brake
            log.warning("ruckig failed on a valid re-plan; this cycle was planned axis by axis (%d so far)",
                        self.planner.fallbacks)
        if self.mode is Mode.IDLE:
            self.robot.hold()
            self._w_ff = np.zeros(3)
        else:
            plan = PlanSample(now, plan_now[0], plan_now[1], p_cmd, self._R_hold, self._w_ff)
            self.robot.command_joint_velocity(joint_velocities(self.model, js, oMtcp, plan, self.params.tick_s,
                                                               self.params.max_speed, self.q_home))
        self._publish_state(now, p, R, twist[:3], est)
        for ev in self.maps.announcements():
            self._event(**ev)
        if self._wd_interval and now - self._wd_last >= self._wd_interval:
            self._wd_last = now
            self.notifier.notify("WATCHDOG=1")

    # -- safety -----------------------------------------------------------------------
    def _check_sensors(self, now: float) -> None:
        """The IMU's faults: stale, or stuck at full scale. Each holds until its condition clears."""
        verdict = safety.imu_staleness(now, self.ring.total, self.ring.last_t, now - self._t_boot, self._late_s,
                                       self._stale_deferred, self.limits)
        self._stale_deferred = verdict.deferred
        self._fault("imu_stale", verdict.stale, keep=verdict.deferred)
        since = self.imu_saturated_since()
        self._fault("imu_saturated", safety.imu_saturation(now, since, self.limits), keep=since is not None)

    def _fault(self, code: str, message: str | None, keep: bool = False) -> None:
        if message is not None and code not in self.faults:
            self.faults[code] = message
            self._event("fault", code=code, message=message)
            self._protective_stop(safety.StopCause(code, message))
        elif message is None and code in self.faults and not keep:
            self.faults.pop(code)
            self._event("fault_cleared", code=code)

    def _check_task(self, js, est) -> None:
        """Force, the estimate's checks and the task's own reactions: a protective stop of the task."""
        if self.mode is not Mode.BUSY:
            return
        if est is not None and (est.onset_t is None or est.onset_t < self._task_t0):
            est = None                                     # an earlier episode's
        cause = safety.check_task(safety.SafetyInput(js.tcp_force, est, self._last_est), self.limits,
                                  self.task.reactions)
        if cause is not None:
            self._protective_stop(cause)
        elif est is not None:
            self._last_est = est

    def _protective_stop(self, cause: safety.StopCause) -> None:
        if self.mode is not Mode.IDLE:
            self._event("protective_stop", cause=cause.cause, message=cause.message, **cause.details)
            self._end_task("failed", error=f"protective stop: {cause.message}")
            self.mode = transition(self.mode, Event.STOP)

    def _internal_fault(self, exc: Exception) -> None:
        """A failed tick: hold the arm, end the task with a protective stop naming the error."""
        try:
            self.robot.hold()
        except Exception:
            log.exception("hold after a failed tick failed")
        self.planner.reset(self.planner.position)
        if self.task is not None:
            self._protective_stop(safety.StopCause("internal", f"control error: {type(exc).__name__}: {exc}"))
        self.mode = transition(self.mode, Event.RESET)
        self._answer_stops()

    # -- commands -------------------------------------------------------------------
    def _handle_commands(self, p: np.ndarray) -> None:
        while self._stops:                       # stop first, whatever else is queued
            stop = self._stops.popleft()
            self._stop_waiters.append(stop.request)
            self._end_task("failed", error=stop.reason)
            self.mode = transition(self.mode, Event.STOP)
        while True:
            try:
                msg = self.commands.get_nowait()
            except queue.Empty:
                return
            if isinstance(msg, Cancel):
                if self.task is None or (msg.task is not None and msg.task != self.task.id):
                    which = "" if msg.task is None else " " + show_name(msg.task)
                    self._reply(msg.request, C.CommandError(C.NO_TASK, f"task: no running task{which}").reply())
                else:
                    self._end_task("failed", error="cancelled")
                    self._reply(msg.request, {"ok": True})
            elif isinstance(msg, StartTask):
                self._reply(msg.request, self._start_task(msg.verb, msg.fields, p))

    def _start_task(self, verb: str, f: dict, p: np.ndarray) -> dict:
        """Start the verb's task from validated fields at the measured TCP position `p`; the command's reply."""
        if self.mode is not Mode.IDLE:
            running = self.task.id if self.task is not None else "a stop"
            return C.CommandError(C.BUSY, f"{verb}: refused, {running} is still running").reply()
        if self.faults:
            code = next(iter(self.faults))
            return C.CommandError(C.FAULT, f"{verb}: refused while fault '{code}' is active").reply()
        spec = verbs.get(verb)
        if spec is None:
            return C.CommandError(C.NOT_IMPLEMENTED, f"verb: '{verb}' is not implemented yet").reply()
        ctx = verbs.TaskContext(f"{verb}-{uuid.uuid4().hex[:8]}", p.copy(),
                                self._R_hold if self._R_hold is not None else np.eye(3), self.params.max_speed,
                                self.params.workspace_min, self.params.workspace_max, self.map_settings,
                                self.maps.write)
        try:
            task = spec.build(f, ctx)
        except verbs.BuildRefused as exc:
            return C.CommandError(C.OUT_OF_LIMITS, str(exc)).reply()
        self.task = task
        self.mode = transition(self.mode, Event.START)
        self._last_est = None
        self._task_saturated = 0
        self._task_t0 = time.monotonic()
        self.planner.reset(p, speed=task.speed)
        self._speed_cap = task.speed
        self._steady_since = None
        # a fresh contact episode for this task; with a trigger phase the trigger is armed once the
        # approach moves at constant speed (the arm's own acceleration at the start looks like an impact)
        self._direct(episode=self._directive.episode + 1, armed=task.trigger_phase is None, begin_t=None)
        self._event("task_started", task=task.id, verb=verb, params=f)
        return {"ok": True, "task": task.id}

    # -- motion ---------------------------------------------------------------------
    def _step_task(self, now: float, p: np.ndarray, R: np.ndarray, est, force) -> np.ndarray:
        """The task's next target, planned; the commanded position one tick ahead."""
        task = self.task
        if est is not None and est.onset_t is not None and est.onset_t >= self._task_t0:
            self._task_saturated = max(self._task_saturated, est.saturated)
            view = ContactView(tracking=True, p=est.p, std=est.std, axis=est.axis, onset_t=est.onset_t,
                               onset_p_tcp=est.onset_p_tcp, in_plane_std=est.in_plane_std, angle_rad=est.angle_rad)
        else:
            view = ContactView(tracking=False)
        if task.trigger_phase is not None:
            self._direct(armed=self._trigger_armed(now, task))
        episode = task.episode
        motion = task.step(TickInput(now, p, R, view, self.planner.at_rest, self.planner.position, force))
        if task.episode != episode:
            # the task starts a fresh contact episode: older onsets no longer count
            self._task_t0 = now
            self._last_est = None
            begin_t = now if task.commanded_onset else None
            task.commanded_onset = False
            self._direct(episode=self._directive.episode + 1, begin_t=begin_t,
                         armed=self._directive.armed if task.trigger_phase is None else False)
        # the task says where its TCP motion along the lever arm is absorbed by the grasp, and where
        # it touches outside an episode (the gyro's bias is then held)
        self._direct(arc_following=task.status.phase in task.absorbed_phases,
                     bias_held=task.status.phase in task.touching_phases)
        if motion is None:
            st = task.status
            if st.state in ("done", "failed"):
                self._end_task(st.state, result=st.result, error=st.error)
            return self._brake_step()
        self._R_hold = motion.R
        self._w_ff = np.zeros(3) if motion.w is None else motion.w
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
        self._protective_stop(cause)
        return self._brake_step()

    def _trigger_armed(self, now: float, task) -> bool:
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
        self._w_ff = np.zeros(3)
        try:
            p_cmd, v_cmd = self.planner.brake()
        except PlannerError:
            p_cmd, v_cmd = self.planner.position, np.zeros(3)
        if self.mode.braking and float(np.linalg.norm(v_cmd)) < REST_SPEED_M_S and self.planner.at_rest:
            self.mode = transition(self.mode, Event.AT_REST)
            self._answer_stops()
        return p_cmd

    def _end_task(self, outcome: str, result: dict | None = None, error: str = "") -> None:
        """End the running task (if any): its end event, a fresh episode for the estimator, and the
        points of a map that ends early written all the same."""
        task = self.task
        if task is None:
            return
        self.task = None
        self.mode = transition(self.mode, Event.END)
        self._direct(episode=self._directive.episode + 1, armed=True, arc_following=False, bias_held=False,
                     begin_t=None)
        if outcome == "done":
            result = dict(result or {})
            if self._task_saturated:
                # said in the result: those samples were left out, the estimate rests on the rest
                result["imu_saturated_samples"] = self._task_saturated
                result["warnings"] = [f"imu_saturated: {self._task_saturated} IMU samples clipped at full scale "
                                      "were left out of the estimate"]
            self._event("task_done", task=task.id, verb=task.kind, result=result)
            return
        extra = {}
        partial = task.partial_record()
        if partial is not None:
            # nothing is lost: the points probed so far are fused and written all the same; the
            # directory appears complete or not at all, and `map_written` says when it has
            self.maps.write_partial(task.id, partial)
            extra["map_pending"] = True
        self._event("task_failed", task=task.id, verb=task.kind, error=error, phase=task.status.phase, **extra)

    # -- out ------------------------------------------------------------------------
    def _direct(self, **changes) -> None:
        """Change what the estimator is told (a latest value: it cannot be lost)."""
        directive = dataclasses.replace(self._directive, **changes)
        if directive != self._directive:
            self._directive = directive
            self.directive.set(directive)

    def _answer_stops(self) -> None:
        for request in self._stop_waiters:
            self._reply(request, {"ok": True})
        self._stop_waiters.clear()

    def _put(self, item) -> None:
        try:
            self.outbox.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _event(self, kind: str, **fields) -> None:
        self._put(("event", {"t": time.monotonic(), "kind": kind, **fields}))

    def _reply(self, request: int | None, payload: dict) -> None:
        if request is not None:
            self.replies.put(Reply(request, payload))

    def _publish_state(self, now: float, p, R, v, est) -> None:
        self._seq += 1
        task = None
        if self.task is not None:
            task = {"id": self.task.id, "kind": self.task.kind, "phase": self.task.status.phase,
                    "progress": round(self.task.status.progress, 4)}
        self._put(("state", {
            "t": now, "seq": self._seq, "mode": self.mode.published(bool(self.faults)),
            "tcp": {"p": p.tolist(), "q": matrix_to_quat(R).tolist(), "v": v.tolist()},
            "contact": None if est is None else est.to_json(),
            "task": task,
            "faults": [{"code": c, "message": m} for c, m in self.faults.items()],
            "control": {**self.stats.snapshot(), "planner_fallbacks": self.planner.fallbacks},
        }))
