"""The 20 ms control thread: the loop that reads the arm, checks safety, takes commands, steps the task and servos.

What it strings together is pure and lives in control/: the task's life with its mode and plan
(control.runner, on control.modes and control.planner), the safety checks (control.safety), the
servo (control.servo), and the tasks (control.tasks, built by their verbs in tecdard/verbs/).
"""
from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np

from tecdard.control import safety
from tecdard.control.geometry import matrix_to_quat
from tecdard.control.modes import Mode
from tecdard.control.planner import CartesianPlanner
from tecdard.control.runner import TaskRunner
from tecdard.control.servo import PlanSample, joint_velocities
from tecdard.api import commands as C
from tecdard import verbs
from tecdard.control.last_hinge import LastHinge
from tecdard.runtime.messages import Cancel, Grip, LatestValue, Outbox, Recover, Reply, StartTask, Stop
from tecdard.runtime.recovery import Recoverer, recover_hint
from tecdard.runtime.realtime import MAX_RT_PRIORITY, TickStats, apply_rt_priority
from tecdard.options import option, read_options
from tecdard.safejson import show_name

log = logging.getLogger("tecdar.control")

WORKSPACE_MAX_M = 5.0         # no arm reaches further from its base: a workspace corner beyond is a typo
COMMAND_QUEUE = 64            # task commands (StartTask, Cancel) waiting for the next tick
STALL_LOG_S = 0.1             # a tick that starts this late is logged (the whole daemon was held up)
IMU_RATE_WINDOW_S = 1.0       # state.imu.rate_hz: the samples the ring took over this long
GRIP_FREE_VERBS = ("home", "wrist")   # tasks that move the arm without needing the object held


@dataclass
class ControlParams:
    """The `control` section: the control loop, its motion limits, and the protective stops."""
    tick_s: float = option(0.02, "the control loop's period", unit="s", minval=0.002, maxval=0.1)
    max_speed: float = 0.05            # limits.max_speed (m/s), given
    max_accel: float = option(0.5, "the TCP's acceleration limit (Ruckig)", unit="m/s^2", above=0.0, maxval=10.0)
    max_jerk: float = option(5.0, "the TCP's jerk limit (Ruckig)", unit="m/s^3", above=0.0, maxval=500.0)
    workspace_min: tuple = option((-1.0, -1.0, 0.0), "the workspace box's lower corner, world", unit="m",
                                  minval=-WORKSPACE_MAX_M, maxval=WORKSPACE_MAX_M)
    workspace_max: tuple = option((1.0, 1.0, 1.5), "the workspace box's upper corner, world", unit="m",
                                  minval=-WORKSPACE_MAX_M, maxval=WORKSPACE_MAX_M)
    imu_stale_s: float = option(0.05, "protective stop when no IMU sample came for this long", unit="s", above=0.0,
                                maxval=1.0)
    max_tracking_error_m: float = option(0.01, "protective stop when the TCP lags its plan by more", unit="m",
                                         above=0.0, maxval=0.1)
    max_force_n: float = option(15.0, "protective stop above this contact force on the TCP", unit="N", above=0.0,
                                maxval=200.0)
    max_rotation_deg: float = option(95.0, "protective stop when the held object has turned more than this",
                                     unit="deg", above=0.0, maxval=360.0)
    max_nis_ratio: float = option(10.0, "protective stop when the estimator's innovations exceed their expected "
                                        "size this much (smoothed NIS ratio)", above=1.0)
    max_contact_jump_m: float = option(0.02, "protective stop when a converged contact estimate moves this far in "
                                             "one tick", unit="m", above=0.0, maxval=1.0)
    contact_rest_s: float = option(1.0, "a contact with no task running (an idle arm's bump, an observed arm's "
                                        "contact) ends once the arm and the fingertip have rested this long; the "
                                        "trigger then re-arms", unit="s", above=0.0, maxval=60.0)
    rt_priority: int | None = option(None, "SCHED_FIFO priority of the control thread where the host allows it "
                                           "(`tecdard doctor`); none: the default scheduler", kind="optint",
                                     minval=1, maxval=MAX_RT_PRIORITY)

    @classmethod
    def from_config(cls, section, max_speed: float) -> "ControlParams":
        p = read_options(cls, section, max_speed=max_speed)
        if any(lo >= hi for lo, hi in zip(p.workspace_min, p.workspace_max)):
            raise section.error("workspace_min", "must be below workspace_max on every axis")
        return p

    def safety_limits(self) -> safety.SafetyLimits:
        return safety.SafetyLimits(
            imu_stale_s=self.imu_stale_s, max_force_n=self.max_force_n, max_rotation_deg=self.max_rotation_deg,
            max_nis_ratio=self.max_nis_ratio, max_contact_jump_m=self.max_contact_jump_m,
            max_tracking_error_m=self.max_tracking_error_m, workspace_min=self.workspace_min,
            workspace_max=self.workspace_max)


def wrench_json(js) -> dict | None:
    """`state.wrench`: the arm's own estimate at the TCP, world frame, as its state gave it: force N, torque N m (None
    where it gives none: the simulator's), and whose estimate (robots.backend.WRENCH_SOURCES)."""
    if js.tcp_force is None or not np.all(np.isfinite(js.tcp_force)):
        return None
    torque = js.tcp_torque
    return {"force_n": [round(float(x), 3) for x in js.tcp_force],
            "torque_nm": None if torque is None or not np.all(np.isfinite(torque)) else
            [round(float(x), 4) for x in torque], "source": js.wrench_source or None}


class ControlThread:
    """Owns the robot's commands, the sensors' faults, and the TaskRunner (mode, task, plan).

    In: task commands through `submit` (StartTask, Cancel; a bounded queue read once per tick) and
    `request_stop` (a Stop from any thread: taken first on every tick, never behind anything).
    Out: a `Reply` per command on `replies` (unbounded: one per request), state and events on
    `outbox`, and what the estimator should do as one `EstimatorDirective` in `directive`. The verbs'
    services (tecdard.verbs.VerbService, by verb) are handed to their tasks; their events are
    published from here.
    """

    def __init__(self, params: ControlParams, model, robot, ring, contact: LatestValue, directive: LatestValue,
                 outbox: Outbox, q_home: np.ndarray, robot_name: str, notifier=None, services: dict | None = None,
                 estimator=None):
        """`estimator`: the estimator thread's side of the tick (runtime.workers.EstimatorThread), or None:
        its `saturated_since` (a latest value: the IMU stream has been clipped since then) is read each
        tick, and `set_resting(resting)` is told whenever the daemon goes idle (True: no task runs, the
        arm held) or a task starts (False)."""
        self.params = params
        self.limits = params.safety_limits()
        self.model = model.clone()           # this thread's own pinocchio Data
        self.robot, self.ring, self.contact, self.outbox = robot, ring, contact, outbox
        self.q_home, self.robot_name, self.notifier = q_home, robot_name, notifier
        self.services = dict(services or {})
        self.estimator = estimator
        self.gripper = None                  # runtime.gripper_worker.GripperWorker once started (None: no gripper)
        self.on_command = None               # on_command(t, qd): each tick's commanded joint rates (zeros: held)
        self.commands: queue.Queue = queue.Queue(maxsize=COMMAND_QUEUE)
        self.replies: queue.SimpleQueue = queue.SimpleQueue()
        self.recoverer = Recoverer(robot, outbox, self.replies,       # `recover`, on a thread of its own
                                   settled=self._recovered)
        self._stops: collections.deque = collections.deque()     # Stop requests, appended from any thread
        self._stop_waiters: list = []
        self.runner = TaskRunner(CartesianPlanner(params.tick_s, params.max_speed, params.max_accel, params.max_jerk),
                                 self.limits, self._event, on_rest=self._answer_stops)
        self.directive = directive
        directive.set(self.runner.directive)
        self.stats = TickStats()
        self.latest_state = LatestValue()    # the newest state message, for `status`
        self.network_fault = LatestValue()   # set by the main thread: why no router reaches the daemon, or None
        self.sensors = safety.SensorWatch(self.limits, time.monotonic())
        self.faults = self.sensors.faults    # code -> message, while it holds
        self._seq = 0
        self._imu_mark = (time.monotonic(), 0)      # (when, ring.total) at the start of the rate's window
        self._imu_rate_hz: float | None = None
        self._resting: bool | None = None
        self._late_s = 0.0                 # how late the current tick started, s
        self.first_tick = threading.Event()
        self._wd_interval = notifier.watchdog_interval_s() if notifier else None
        self._wd_last = 0.0
        self.last_hinge: LastHinge | None = None    # the last rotate's: the next one's default direction

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
        """No task, the arm at rest after any stop, and every verb's service idle (a map written), for
        an orderly shutdown."""
        return self.runner.mode is Mode.IDLE and all(s.idle for s in self.services.values())

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
                if self._late_s > STALL_LOG_S:
                    # said, so that a stale-IMU stop after it can be told from a stalled sensor
                    log.warning("control tick started %.0f ms late: the daemon was stalled", self._late_s * 1e3)
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
            for service in self.services.values():
                try:
                    service.shutdown()
                except Exception:
                    log.exception("shutting down a verb's service failed")
            self.runner.planner.release()

    def _recovered(self) -> bool:
        """(the recover thread) No fault that `recover` clears is held at the tick."""
        try:
            return not set(self.faults) & self.robot.recoverable
        except RuntimeError:                 # the tick changed the faults meanwhile: asked again
            return False

    def tick(self, now: float) -> None:
        runner = self.runner
        planner = runner.planner
        planner.advance(now)
        js = self.robot.read_state()
        fresh = now - js.t <= self.robot.state_age_s     # the servo never commands from an older state
        oMtcp, twist = self.model.measured(js)
        p, R = oMtcp.translation.copy(), oMtcp.rotation.copy()
        est = self.contact.get()
        self._check_sensors(now, p, self.robot.state_seen_t(js))
        runner.check(js.tcp_force, est)
        self._handle_commands(now, p, js)
        p_plan, v_plan = planner.position, planner.velocity
        fallbacks = planner.fallbacks
        p_cmd = runner.step(now, p, R, est, js.tcp_force, np.asarray(js.q, dtype=float), js.t, twist[:3])
        runner.end_idle_episode(now, twist[:3], est, self.params.contact_rest_s, faulted=bool(self.faults))
        if planner.fallbacks != fallbacks:     # a task's step or a brake
            log.warning("ruckig failed on a valid re-plan; this cycle was planned axis by axis (%d so far)",
                        planner.fallbacks)
        if p_cmd is None or not fresh:
            self.robot.hold()
            qd_sent = np.zeros(len(js.q))
        elif runner.qd_cmd is not None:           # a joint-space task (home)
            qd_sent = runner.qd_cmd
            self.robot.command_joint_velocity(qd_sent)
        else:
            plan = PlanSample(now, p_plan, v_plan, p_cmd, runner.R_hold, runner.w_ff)
            qd_sent = joint_velocities(self.model, js, oMtcp, plan, self.params.tick_s, self.params.max_speed,
                                       self.q_home)
            self.robot.command_joint_velocity(qd_sent)
        if self.on_command is not None:           # the recorder's (a recording's live_cmd: the tick's action)
            self.on_command(now, qd_sent)
        if self.estimator is not None:            # the onset trigger's (control.command_track)
            self.estimator.note_command(now, qd_sent)
        if self.directive.get() is not runner.directive:
            self.directive.set(runner.directive)
        resting = runner.mode is Mode.IDLE
        if resting is not self._resting:
            if self.estimator is not None:
                self.estimator.set_resting(resting)
            self.robot.set_resting(resting)
        self._resting = resting
        self._publish_state(now, p, R, twist[:3], est, js)
        for service in self.services.values():
            for ev in service.announcements():
                self._event(**ev)
        if self._wd_interval and now - self._wd_last >= self._wd_interval:
            self._wd_last = now
            self.notifier.notify("WATCHDOG=1")

    # -- faults -------------------------------------------------------------------------
    def _check_sensors(self, now: float, p: np.ndarray, state_t: float) -> None:
        """The IMU's faults (stale, stuck at full scale) and the robot's (its newest state too old, a
        state refused, a backend's faults()): a new one stops the running task. `p`: the measured
        TCP, `state_t`: when the newest robot state was measured."""
        robot = self.robot
        changes = [(c, None) for c in self.sensors.update(now, self.ring.total, self.ring.last_t, self._late_s,
                                                           None if self.estimator is None else
                                                           self.estimator.saturated_since)]
        # the robot's own controller has stopped the arm where it is: the plan stops there too
        changes += [(c, p) for c in self.sensors.update_state_age(now, state_t, robot.state_age_s, self._late_s)]
        backend = {c: m + recover_hint(c, robot.recoverable)
                   for c, m in {**robot.faults(), **robot.state_faults()}.items()}
        # the daemon cut from its Zenoh router (network.RouterLink): no command, `stop` included, can
        # reach it, so the task stops as on a lost robot link, braking on its plan (the arm still obeys)
        net = self.network_fault.get()
        current = backend if net is None or "robot_link" in backend else {**backend, "robot_link": net}
        changes += [(c, p if c[1] in backend else None) for c in self.sensors.update_robot(current)]
        for (kind, code, message), halted_at in changes:
            if kind == "fault":
                self._event("fault", code=code, message=message)
                self.runner.protective_stop(safety.StopCause(code, message), halted_at=halted_at)
            else:
                self._event("fault_cleared", code=code)

    def _internal_fault(self, exc: Exception) -> None:
        """A failed tick: hold the arm, end the task with a protective stop naming the error."""
        try:
            self.robot.hold()
        except Exception:
            log.exception("hold after a failed tick failed")
        if self.runner.task is not None:
            self.runner.protective_stop(safety.StopCause("internal", f"control error: {type(exc).__name__}: {exc}"))
        self.runner.reset()
        self._answer_stops()

    # -- commands -------------------------------------------------------------------
    def _handle_commands(self, now: float, p: np.ndarray, js) -> None:
        while self._stops:                       # stop first, whatever else is queued
            stop = self._stops.popleft()
            self._stop_waiters.append(stop.request)
            self.runner.stop(stop.reason)
            if self.gripper is not None and self.gripper.busy:
                self.gripper.stop()              # the fingers too, where they are
        while True:
            try:
                msg = self.commands.get_nowait()
            except queue.Empty:
                return
            if isinstance(msg, Cancel):
                if self.runner.cancel(msg.task):
                    self._reply(msg.request, {"ok": True})
                else:
                    which = "" if msg.task is None else " " + show_name(msg.task)
                    self._reply(msg.request, C.CommandError(C.NO_TASK, f"task: no running task{which}").reply())
            elif isinstance(msg, StartTask):
                self._reply(msg.request, self._start_task(msg.verb, msg.fields, now, p, js))
            elif isinstance(msg, Recover):
                running = self._occupied() or ("the gripper" if self.gripper is not None and self.gripper.busy else None)
                if running is not None:
                    self._reply(msg.request, C.CommandError(C.BUSY, f"recover: refused, {running} is still running").reply())
                else:
                    self.recoverer.start(msg.request)
            elif isinstance(msg, Grip):
                refused = self._grip_refusal(msg)
                if refused is not None:
                    self._reply(msg.request, refused)
                else:
                    self.last_hinge = None       # a grasp or a release: the object held may not be the one turned

    def _occupied(self) -> str | None:
        """What keeps a task, a grip command or `recover` from starting: the running task, or a recovery."""
        return self.runner.busy() or ("a recovery" if self.recoverer.busy else None)

    def _grip_refusal(self, msg: Grip) -> dict | None:
        """Hand a grasp or a release to the gripper's thread (it replies when the fingers stop), or the refusal:
        never during a task or a fault (the object is the task's, and a faulted arm's), one at a time."""
        running = self._occupied()
        if self.gripper is None:
            return C.CommandError(C.NO_GRIPPER, f"{msg.verb}: no gripper here (gripper.backend: none); set "
                                                "gripper.backend (manual, if a person grasps)").reply()
        if running is not None:
            return C.CommandError(C.BUSY, f"{msg.verb}: refused, {running} is still running").reply()
        # a protective stop held by a contact's force is freed by letting go of the object (the arm itself holds):
        # `release` is the one grip command a protective stop allows
        if self.faults and not (msg.verb == "release" and set(self.faults) <= {"robot_protective_stop"}):
            return C.CommandError(C.FAULT, f"{msg.verb}: refused while fault '{next(iter(self.faults))}' "
                                           "is active").reply()
        force = msg.fields.get("force_n")
        if force is not None and force > self.gripper.params.max_force_n:
            return C.CommandError(C.OUT_OF_LIMITS, f"force: {force:g} N is above gripper.max_force_n "
                                                   f"{self.gripper.params.max_force_n:g} N").reply()
        if not self.gripper.submit(msg):
            return C.CommandError(C.BUSY, f"{msg.verb}: refused, the gripper is still moving").reply()
        return None

    def _start_task(self, verb: str, f: dict, now: float, p: np.ndarray, js) -> dict:
        """Start the verb's task from validated fields at the measured TCP position `p` (of the tick's
        joint state `js`); the command's reply."""
        running = self._occupied()
        if running is not None:
            return C.CommandError(C.BUSY, f"{verb}: refused, {running} is still running").reply()
        if self.faults:
            code = next(iter(self.faults))
            return C.CommandError(C.FAULT, f"{verb}: refused while fault '{code}' is active").reply()
        refused = self._refused_without_grasp(verb)
        if refused is not None:
            return refused
        spec = verbs.get(verb)
        if spec is None:
            return C.CommandError(C.NOT_IMPLEMENTED, f"verb: '{verb}' is not implemented yet").reply()
        direction_from = None
        if verb == "rotate":
            f, direction_from = self._rotate_direction(f, p)
        R_hold = self.runner.R_hold if self.runner.R_hold is not None else np.eye(3)
        ctx = verbs.TaskContext(f"{verb}-{uuid.uuid4().hex[:8]}", p.copy(), R_hold, self.params.max_speed,
                                self.params.workspace_min, self.params.workspace_max, self.services.get(verb),
                                q=np.array(js.q, dtype=float), q_home=np.array(self.q_home, dtype=float),
                                fk=lambda q: self.model.fk(q).translation.copy(),
                                world=self.robot.world_control)
        try:
            task = spec.build(f, ctx)
        except verbs.BuildRefused as exc:
            return C.CommandError(C.OUT_OF_LIMITS, str(exc)).reply()
        if direction_from is None:
            self.runner.start(task, now, p, f)
            return {"ok": True, "task": task.id}
        log.info("%s: direction %s, %s", task.id, np.round(f["direction"], 3).tolist(), direction_from)
        self.runner.start(task, now, p, {**f, "direction_from": direction_from})
        return {"ok": True, "task": task.id, "direction": f["direction"], "direction_from": direction_from}

    def _refused_without_grasp(self, verb: str) -> dict | None:
        """A task needs the object held: refused while the gripper moves, or says it holds nothing (`home`, which
        moves the arm without a contact, goes on)."""
        g = self.gripper
        if g is None or verb in GRIP_FREE_VERBS:
            return None
        if g.busy:
            return C.CommandError(C.BUSY, f"{verb}: refused, the gripper is still moving").reply()
        if g.holds_nothing():
            width = g.state().width_m
            return C.CommandError(C.NOT_GRASPED, f"{verb}: refused, the {g.kind} gripper holds nothing"
                                  + ("" if width is None else f" (opening {width * 1e3:.1f} mm)")
                                  + ": grasp the object first (tecdard grasp --force N)").reply()
        return None

    # -- out ------------------------------------------------------------------------
    def _answer_stops(self) -> None:
        for request in self._stop_waiters:
            self._reply(request, {"ok": True})
        self._stop_waiters.clear()

    def _event(self, kind: str, **fields) -> None:
        if kind == "task_done" and fields.get("verb") == "rotate":
            self.last_hinge = LastHinge.from_result(fields["task"], fields.get("result") or {})
        elif kind == "task_failed" and fields.get("verb") == "rotate":
            self.last_hinge = None           # the handle stood wherever the failure left it
        self.outbox.event(kind, **fields)

    def _rotate_direction(self, f: dict, p: np.ndarray) -> tuple[dict, str | None]:
        """A rotate without a `direction` after a rotate: the tangent at the grasp about the hinge it found, where
        the TCP still lies on that hinge's circle (control/last_hinge.py). The fields, and what chose the
        direction (None: the payload's, or the configured default with no hinge known)."""
        if "direction" in getattr(f, "given", ("direction",)) or self.last_hinge is None:
            return f, None
        t, why = self.last_hinge.tangent(p)
        if t is None:
            return f, f"the configured default ({why})"
        return {**f, "direction": [float(x) for x in t]}, why

    def _reply(self, request: int | None, payload: dict) -> None:
        if request is not None:
            self.replies.put(Reply(request, payload))

    def _gripper_json(self) -> dict:
        g = self.gripper
        return {**g.state().to_json(g.kind), "busy": g.busy}

    def _source(self):
        """The IMU source (drivers.imu_source.ImuSource) the estimator thread reads, or None."""
        return getattr(self.estimator, "source", None)

    def _source_faults(self) -> dict[str, str]:
        source = self._source()
        return {} if source is None else source.faults()

    def _imu_part(self) -> str | None:
        """The IMU source's sensor (drivers.imu_source.ImuSource.part), None when it cannot say."""
        source = self._source()
        return None if source is None else source.part

    def _imu_lost_s(self) -> float | None:
        """How long ago the IMU source's board was lost (its port gone), None while it is there."""
        source = self._source()
        return None if source is None else source.lost_s()

    def _publish_state(self, now: float, p, R, v, est, js) -> None:
        self._seq += 1
        tcp_t = js.t
        task = self.runner.task
        t_mark, n_mark = self._imu_mark
        if now - t_mark >= IMU_RATE_WINDOW_S:
            total = self.ring.total
            self._imu_rate_hz = round((total - n_mark) / (now - t_mark), 1)
            self._imu_mark = (now, total)
        state = {
            "t": now, "seq": self._seq, "mode": self.runner.mode.published(bool(self.faults)),
            "tcp": {"p": p.tolist(), "q": matrix_to_quat(R).tolist(), "v": v.tolist()},
            "tcp_t": tcp_t if math.isfinite(tcp_t) else None,     # when the robot measured that TCP
            "contact": None if est is None else est.to_json(),
            "task": None if task is None else {"id": task.id, "kind": task.kind, "phase": task.status.phase,
                                               "progress": round(task.status.progress, 4)},
            # the daemon's faults, then the IMU source's own as they stand (a lost port: since when)
            "faults": [{"code": c, "message": m} for c, m in {**self._source_faults(), **self.faults}.items()],
            "control": {**self.stats.snapshot(), "planner_fallbacks": self.runner.planner.fallbacks,
                        "outbox_dropped": self.outbox.counts(), "imu_overwritten": self.ring.overwritten},
            # samples a second the daemon took (None in the first second), and the sensor the board found
            "imu": {"rate_hz": self._imu_rate_hz, "part": self._imu_part(), "lost_s": self._imu_lost_s()},
            # the gripper: its opening, force and where that comes from, whether it holds (None: no gripper)
            "gripper": None if self.gripper is None else self._gripper_json(),
            # the arm's own estimate of the external wrench at the TCP (None where it estimates no force)
            "wrench": wrench_json(js),
        }
        self.latest_state.set(state)
        self.outbox.put("state", state)
