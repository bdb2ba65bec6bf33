"""The 20 ms control thread: FK, safety, task state machine, Ruckig re-plan, DLS IK, joint commands."""
from __future__ import annotations

import collections
import concurrent.futures
import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np

from control.planner import CartesianPlanner, PlannerError
from control.mapping import MapParams, MapTask
from control.tasks import ApproachTask, ContactView, PointTask, ProbeTask, RotateTask, TickInput
from control.geometry import matrix_to_quat, rotvec_to_matrix
from tecdard import commands as C
from tecdard.mapfiles import MapSettings, write_map
from tecdard.messages import Cancel, Reply, StartTask, Stop
from tecdard.realtime import MAX_RT_PRIORITY, apply_rt_priority
from tecdard.safejson import show_name

log = logging.getLogger("tecdar.control")

TICK_STATS_WINDOW = 1000      # ticks kept for percentiles
WORKSPACE_MAX_M = 5.0         # no arm reaches further from its base: a workspace corner beyond is a typo
COMMAND_QUEUE = 64            # task commands (StartTask, Cancel) waiting for the next tick
TICK_STATS_EVERY = 25         # recompute percentiles every this many ticks
REST_SPEED_M_S = 1e-3         # the TCP counts as stopped below this speed
IMU_STARTUP_GRACE_S = 1.0     # no stale-IMU fault before the first sample until this long after start
SERVO_MAX_AGE_S = 0.1         # the servo compares a measurement with the plan this far back at most
# A tick that starts this late means the daemon itself was stalled (the machine, the GIL): the IMU's
# samples may be waiting in the acquisition thread's queue, so staleness is judged on the next tick
# (once; a second late tick judges it all the same).
STALE_JUDGE_LATE_S = 0.01
MAP_AIM_MARGIN_M = 0.01      # a map's planned TCP positions keep this far inside the workspace box (x, y)
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


class LatestValue:
    """A single-slot buffer: one writer replaces, readers take the newest."""

    def __init__(self, value=None):
        self._lock = threading.Lock()
        self._value = value

    def set(self, value) -> None:
        with self._lock:
            self._value = value

    def get(self):
        with self._lock:
            return self._value


class TickStats:
    def __init__(self):
        self.ticks = 0
        self.overruns = 0
        self._work = np.zeros(TICK_STATS_WINDOW)
        self._late = np.zeros(TICK_STATS_WINDOW)
        self.summary = {}

    def add(self, work_s: float, late_s: float) -> None:
        i = self.ticks % TICK_STATS_WINDOW
        self._work[i] = work_s
        self._late[i] = late_s
        self.ticks += 1
        if self.ticks % TICK_STATS_EVERY == 0:
            n = min(self.ticks, TICK_STATS_WINDOW)
            w, lt = self._work[:n] * 1e3, self._late[:n] * 1e3
            self.summary = {
                "ticks": self.ticks, "overruns": self.overruns,
                "work_ms_p50": round(float(np.median(w)), 3), "work_ms_p99": round(float(np.percentile(w, 99)), 3),
                "work_ms_max": round(float(w.max()), 3),
                "late_ms_p50": round(float(np.median(lt)), 3), "late_ms_p99": round(float(np.percentile(lt, 99)), 3),
                "late_ms_max": round(float(lt.max()), 3),
            }

    def snapshot(self) -> dict:
        out = dict(self.summary)
        out["ticks"] = self.ticks
        out["overruns"] = self.overruns
        return out


class ControlThread:
    """Owns the task, the planner and the robot commands. Everything else reaches it
    through `submit` (StartTask and Cancel from the Zenoh thread) and `request_stop` (a Stop,
    from any thread: checked first on every tick, never queued behind anything). It hands
    results out through `replies` (a Reply per command), `outbox` (state and events) and
    `to_estimator` (the task's wishes of the estimator: release, arm, begin, arc, hold_bias;
    proprioception reaches the estimator from its own thread, tecdard.workers.proprio_loop).
    """

    def __init__(self, params: ControlParams, model, robot, ring, contact: LatestValue,
                 to_estimator: queue.Queue, outbox: queue.Queue, q_home: np.ndarray, robot_name: str,
                 notifier=None, map_settings: MapSettings | None = None, imu_saturated_since=None):
        self.p = params
        self.model = model.clone()
        self.robot = robot
        self.ring = ring
        self.contact = contact
        self.to_estimator = to_estimator
        self.outbox = outbox
        self.q_home = q_home
        self.robot_name = robot_name
        self.notifier = notifier
        self.map_settings = map_settings or MapSettings()
        self.imu_saturated_since = imu_saturated_since or (lambda: None)   # latest value of the estimator thread
        self._task_saturated = 0            # IMU samples clipped at full scale in the running task's episodes
        # map files are fused and written here, never on the 20 ms tick
        self._writer = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-writer")
        self._writes: list[concurrent.futures.Future] = []
        self._partial_maps: list[tuple[str, concurrent.futures.Future]] = []   # (task id, write) of failed maps
        self.commands: queue.Queue = queue.Queue(maxsize=COMMAND_QUEUE)
        self.replies: queue.SimpleQueue = queue.SimpleQueue()    # as many as there are requests: never full
        self._stops: collections.deque = collections.deque()     # Stop requests, appended from any thread
        self.planner = CartesianPlanner(params.tick_s, params.max_speed, params.max_accel, params.max_jerk)
        self.stats = TickStats()
        self.task = None
        self.mode = "idle"
        self.faults: dict[str, str] = {}
        self._braking = False
        self._stop_waiters: list = []
        self._seq = 0
        self._R_hold = None
        self._w_ff = np.zeros(3)           # angular velocity feed-forward of the orientation target
        self._speed_cap = None             # the planner's current TCP speed cap, m/s
        self._episode = 0
        self._task_t0 = 0.0
        self._trigger_armed = True
        self._steady_since = None          # when the plan last became steady in the trigger's phase
        self._last_est = None              # the contact estimate seen on the previous tick
        self._t_boot = time.monotonic()
        self.first_tick = threading.Event()
        self.dropped = 0
        self._late_s = 0.0                 # how late the current tick started, s
        self._stale_deferred = False
        self._wd_interval = notifier.watchdog_interval_s() if notifier else None
        self._wd_last = 0.0

    # -- outbox helpers (never block the tick) ------------------------------
    def _put(self, item, queue_: queue.Queue | None = None) -> None:
        try:
            (queue_ or self.outbox).put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _event(self, kind: str, **fields) -> None:
        self._put(("event", {"t": time.monotonic(), "kind": kind, **fields}))

    def _reply(self, request: int | None, payload: dict) -> None:
        if request is not None:
            self.replies.put(Reply(request, payload))

    def _write_map(self, record) -> concurrent.futures.Future:
        """Fuse and write a map on the map-writer thread, never on the tick."""
        fut = self._writer.submit(write_map, record, self.map_settings)
        self._writes = [f for f in self._writes if not f.done()] + [fut]
        return fut

    def _announce_partial_maps(self) -> None:
        """A failed map's files, once written: `map_written` (or `map_write_failed`)."""
        for item in [m for m in self._partial_maps if m[1].done()]:
            self._partial_maps.remove(item)
            task_id, fut = item
            exc = fut.exception()
            if exc is None:
                res = fut.result()
                self._event("map_written", task=task_id, map_path=res["path"], files=res["files"],
                            summary=res["summary"])
            else:
                log.error("map %s: the points probed were not written: %s", task_id, exc)
                self._event("map_write_failed", task=task_id, error=f"{type(exc).__name__}: {exc}")

    def quiescent(self) -> bool:
        """No task, the arm at rest after any stop, and every map written (for an orderly shutdown)."""
        return self.task is None and not self._braking and all(f.done() for f in self._writes)

    # -- commands in (any thread) --------------------------------------------
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

    # -- thread body --------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        apply_rt_priority(self.p.rt_priority)
        t_next = time.monotonic()
        failures = 0
        try:
            while not stop.is_set():
                t_next += self.p.tick_s
                t0 = time.monotonic()
                self._late_s = max(0.0, t0 - (t_next - self.p.tick_s))
                try:
                    self.tick(t0)
                    failures = 0
                except Exception as exc:      # a bug must not leave the arm moving or the daemon deaf
                    failures += 1
                    if failures == 1 or failures % 50 == 0:
                        log.exception("control tick failed (%d in a row)", failures)
                    self._internal_fault(exc)
                self.first_tick.set()
                t1 = time.monotonic()
                self.stats.add(t1 - t0, self._late_s)
                delay = t_next - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    # Late: the next tick runs now, and the periods missed altogether are skipped
                    # (the plan follows wall time, so a burst of catch-up ticks would only cost CPU).
                    self.stats.overruns += 1
                    t_next += math.floor(-delay / self.p.tick_s) * self.p.tick_s
        finally:
            try:
                self.robot.hold()
            except Exception:
                log.exception("hold on exit failed")
            self._writer.shutdown(wait=False, cancel_futures=True)

    def tick(self, now: float) -> None:
        self.planner.advance(now)
        js = self.robot.read_state()
        oMtcp, twist = self.model.measured(js)
        p, R = oMtcp.translation.copy(), oMtcp.rotation.copy()
        v, w = twist[:3].copy(), twist[3:].copy()
        est = self.contact.get()
        self._check_faults(now)
        self._check_saturation(now)
        self._check_limits(js, est)
        self._handle_commands(p, v)
        p_plan, v_plan = self.planner.position, self.planner.velocity
        fallbacks = self.planner.fallbacks
        if self.task is not None and not self._braking:
            p_cmd, v_cmd = self._step_task(now, p, R, est, js.tcp_force)
        elif self._braking or self.mode == "stopped":
            p_cmd, v_cmd = self._brake_step()
        else:
            self.planner.reset(p)
            p_plan, v_plan, p_cmd, v_cmd = p, np.zeros(3), p, np.zeros(3)
            if self._R_hold is None:
                self._R_hold = R
        if self.planner.fallbacks != fallbacks:     # a task's step or a brake
            log.warning("ruckig failed on a valid re-plan; this cycle was planned axis by axis (%d so far)",
                        self.planner.fallbacks)
        if self.mode == "idle" and self.task is None and not self._braking:
            self.robot.hold()
            self._R_hold = R
            self._w_ff = np.zeros(3)
        else:
            v_ff = (p_cmd - p_plan) / self.p.tick_s
            # The plan is at `now`, the measurement at js.t, a proprioception period or more
            # earlier: the servo compares it with the plan at that time. Against the plan at
            # `now` the feedback would add gain * v * age, which changes with the age each tick
            # (a sawtooth of velocity steps that the IMU's trigger can feel).
            age = min(max(now - js.t, 0.0), SERVO_MAX_AGE_S)
            p_ref = p_plan - v_plan * age
            R_ref = rotvec_to_matrix(-self._w_ff * age) @ self._R_hold
            tw = self.model.servo_twist(oMtcp, p_ref, v_ff, R_ref, self._w_ff)
            speed = float(np.linalg.norm(tw[:3]))
            if speed > self.p.max_speed:       # hard TCP speed bound, whatever the planner said
                tw[:3] *= self.p.max_speed / speed
            qd = self.model.dls_velocity(js.q, tw, self.q_home)
            self.robot.command_joint_velocity(qd)
        self._publish_state(now, p, R, v, est)
        if self._partial_maps:
            self._announce_partial_maps()
        if self._wd_interval and now - self._wd_last >= self._wd_interval:
            self._wd_last = now
            self.notifier.notify("WATCHDOG=1")

    # -- safety ---------------------------------------------------------------
    def _check_faults(self, now: float) -> None:
        if self.ring.total == 0 and now - self._t_boot < IMU_STARTUP_GRACE_S:
            return     # the first samples are still on their way
        age = now - self.ring.last_t
        if age <= self.p.imu_stale_s:
            self._stale_deferred = False
            if "imu_stale" in self.faults:
                self._clear_fault("imu_stale")
            return
        if "imu_stale" in self.faults:
            return
        if self._late_s > STALE_JUDGE_LATE_S and not self._stale_deferred:
            self._stale_deferred = True            # our own stall: judge on the next tick
            return
        self._stale_deferred = False
        if self.ring.total == 0:
            self._set_fault("imu_stale", f"no IMU sample since the start, {(now - self._t_boot) * 1e3:.0f} ms ago "
                                         f"(limit {self.p.imu_stale_s * 1e3:.0f} ms)")
            return
        self._set_fault("imu_stale", f"no IMU sample for {age * 1e3:.0f} ms (limit {self.p.imu_stale_s * 1e3:.0f} ms)")

    def _check_saturation(self, now: float) -> None:
        """A stream clipped at full scale for longer than imu_stale_s is a sensor fault (stuck, or
        overloaded): no contact can be measured from it. A single clipped impact is not."""
        since = self.imu_saturated_since()
        if since is not None and now - since > self.p.imu_stale_s:
            if "imu_saturated" not in self.faults:
                self._set_fault("imu_saturated", f"the IMU has read full scale for {(now - since) * 1e3:.0f} ms "
                                                 f"(limit {self.p.imu_stale_s * 1e3:.0f} ms)")
        elif since is None and "imu_saturated" in self.faults:
            self._clear_fault("imu_saturated")

    def _check_limits(self, js, est) -> None:
        """Force and rotation thresholds: a protective stop of the running task."""
        if self.task is None or self._braking:
            return
        if js.tcp_force is not None:
            f = float(np.linalg.norm(js.tcp_force))
            if f > self.p.max_force_n:
                self._protective_stop("force", f"TCP force {f:.1f} N over the limit {self.p.max_force_n:.1f} N",
                                      force_n=f)
                return
        if est is None or est.onset_t is None or est.onset_t < self._task_t0:
            return
        angle = math.degrees(est.angle_rad)
        if angle > self.p.max_rotation_deg:
            self._protective_stop("rotation", f"object turned {angle:.1f} deg, over the limit "
                                              f"{self.p.max_rotation_deg:.1f} deg", angle_deg=angle)
            return
        if est.nis_ratio is not None and est.nis_ratio > self.p.max_nis_ratio:
            # the measurements stopped fitting the contact model: a slip, a moving hinge, a bad sensor
            self._protective_stop("divergence", f"estimator innovations {est.nis_ratio:.0f}x their expected size "
                                                f"(limit {self.p.max_nis_ratio:.0f}x)", nis_ratio=est.nis_ratio)
            return
        prev, self._last_est = self._last_est, est
        if prev is not None and prev.onset_t == est.onset_t and prev.converged and prev is not est:
            d = est.p - prev.p
            if est.axis is not None:
                d = d - float(np.dot(d, est.axis)) * est.axis     # along a line contact: unobservable
            jump = float(np.linalg.norm(d))
            if jump > self.p.max_contact_jump_m:
                self._protective_stop("contact_jump", f"contact estimate moved {jump * 1e3:.1f} mm in one tick "
                                                      f"(limit {self.p.max_contact_jump_m * 1e3:.0f} mm)",
                                      jump_m=jump)

    def _internal_fault(self, exc: Exception) -> None:
        """A failed tick: hold the arm, end the task with a protective stop naming the error."""
        try:
            self.robot.hold()
        except Exception:
            log.exception("hold after a failed tick failed")
        self.planner.reset(self.planner.position)
        if self.task is not None:
            self._protective_stop("internal", f"control error: {type(exc).__name__}: {exc}")
        self._braking = False
        self.mode = "idle" if self.task is None else self.mode

    def _set_fault(self, code: str, message: str) -> None:
        self.faults[code] = message
        self._event("fault", code=code, message=message)
        self._protective_stop(code, message)

    def _clear_fault(self, code: str) -> None:
        self.faults.pop(code, None)
        self._event("fault_cleared", code=code)

    def _protective_stop(self, cause: str, message: str, **details) -> None:
        if self.task is not None or self._braking or self.mode == "busy":
            self._event("protective_stop", cause=cause, message=message, **details)
            self._end_task("failed", error=f"protective stop: {message}")
            self._braking = True
            self.mode = "stopped"          # until the arm is at rest, then idle

    # -- commands ---------------------------------------------------------------
    def _handle_commands(self, p: np.ndarray, v: np.ndarray) -> None:
        while self._stops:                       # stop first, whatever else is queued
            stop = self._stops.popleft()
            self._stop_waiters.append(stop.request)
            if self.task is not None:
                self._end_task("failed", error=stop.reason)
            self._braking = True
            self.mode = "stopped"
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
                    self._braking = True
                    self._reply(msg.request, {"ok": True})
            elif isinstance(msg, StartTask):
                self._start_task(msg.verb, msg.fields, msg.request, p, v)

    def _start_task(self, verb: str, f: dict, request: int | None, p: np.ndarray, v: np.ndarray) -> None:
        if self.task is not None or self._braking:
            running = self.task.id if self.task is not None else "a stop"
            self._reply(request, C.CommandError(C.BUSY, f"{verb}: refused, {running} is still running").reply())
            return
        if self.faults:
            code = next(iter(self.faults))
            self._reply(request, C.CommandError(C.FAULT, f"{verb}: refused while fault '{code}' is active").reply())
            return
        task_id = f"{verb}-{uuid.uuid4().hex[:8]}"
        if verb == "rotate":
            task = RotateTask(task_id, math.radians(f["angle_deg"]), f["speed"], f["probe_distance"],
                              np.array(f["direction"]), f["strategy"], turn_tool=f["turn_tool"])
        elif verb == "probe":
            task = ProbeTask(task_id, f["speed"], f["distance"], np.array(f["direction"]))
        elif verb == "point":
            task = PointTask(task_id, f["radius"], f["speed"], f["turns"])
        elif verb == "approach":
            task = ApproachTask(task_id, np.array(f["direction"]), f["speed"], f["max_distance"], math.radians(f["stop_angle_deg"]))
        elif verb == "map":
            try:
                task = self._map_task(task_id, f, p)
            except C.CommandError as exc:
                self._reply(request, exc.reply())
                return
        else:
            self._reply(request, C.CommandError(C.NOT_IMPLEMENTED, f"verb: '{verb}' is not implemented yet").reply())
            return
        self.task = task
        self._last_est = None
        self._task_saturated = 0
        self._task_t0 = time.monotonic()
        self.mode = "busy"
        self.planner.reset(p, speed=f["speed"])
        self._speed_cap = f["speed"]
        self._episode = task.episode
        self._put(("release",), self.to_estimator)     # fresh contact episode for this task
        self._trigger_armed = task.trigger_phase is None
        if not self._trigger_armed:
            # the arm's own acceleration at the start would look like an impact: the trigger is
            # armed once the approach moves at constant speed (as the paper's ongoing case does)
            self._put(("arm", False), self.to_estimator)
        self._event("task_started", task=task_id, verb=verb, params=f)
        self._reply(request, {"ok": True, "task": task_id})

    def _map_task(self, task_id: str, f: dict, p: np.ndarray) -> MapTask:
        """A map run from the command; refused when any of its moves would leave the workspace box."""
        ms = self.map_settings
        size = np.array(f["size"])
        origin = np.array(f["origin"]) if f["origin"] is not None else p[:2] - size / 2
        # Ruckig caps each axis: a diagonal travel at max_speed / sqrt(2) stays within max_speed
        params = MapParams(origin_xy=origin, size_xy=size, grid=tuple(f["grid"]), depth=f["depth"],
                           orientations=f["orientations"], speed=f["speed"], travel_speed=self.p.max_speed / math.sqrt(2.0),
                           probe_distance=ms.probe_distance_m, abort_force_n=ms.abort_force_n,
                           max_point_std_m=ms.max_point_std_m, tool_tip_tcp=np.array(ms.tool_tip_tcp),
                           turn_yaw_rad=math.radians(ms.turn_deg), release_distance=ms.release_distance_m)
        task = MapTask(task_id, params, lambda record: self._write_map(record))
        lo, hi = np.array(self.p.workspace_min), np.array(self.p.workspace_max)
        for name, z in (("origin", p[2]), ("depth", p[2] - f["depth"])):
            for xy in task.planned_tcp_xy(self._R_hold if self._R_hold is not None else np.eye(3)):
                q = np.array([xy[0], xy[1], z])
                # the tool model aims the TCP; what each probe measures refines it by millimetres
                if np.any(q < lo + [MAP_AIM_MARGIN_M, MAP_AIM_MARGIN_M, 0.0]) or \
                        np.any(q > hi - [MAP_AIM_MARGIN_M, MAP_AIM_MARGIN_M, 0.0]):
                    raise C.CommandError(C.OUT_OF_LIMITS, f"{name}: the map takes the TCP to "
                                                          f"{np.round(q, 3).tolist()}, outside the workspace box")
        return task

    # -- motion ---------------------------------------------------------------
    def _step_task(self, now: float, p: np.ndarray, R: np.ndarray, est, force) -> tuple[np.ndarray, np.ndarray]:
        task = self.task
        if est is not None and est.onset_t is not None and est.onset_t >= self._task_t0:
            self._task_saturated = max(self._task_saturated, est.saturated)
            view = ContactView(tracking=True, p=est.p, std=est.std, axis=est.axis, onset_t=est.onset_t,
                               onset_p_tcp=est.onset_p_tcp,
                               in_plane_std=est.in_plane_std, angle_rad=est.angle_rad)
        else:
            view = ContactView(tracking=False)
        phase_before = task.status.phase
        if task.trigger_phase is not None:
            # armed while the arm moves steadily (TRIGGER_SETTLE_S after the plan does): starting and
            # braking are not impacts
            steady = task.status.phase == task.trigger_phase and self.planner.steady(task.speed)
            if not steady:
                self._steady_since = None
            elif self._steady_since is None:
                self._steady_since = now
            steady = steady and now - self._steady_since >= TRIGGER_SETTLE_S
            if steady != self._trigger_armed:
                self._trigger_armed = steady
                self._put(("arm", steady), self.to_estimator)
        motion = task.step(TickInput(now, p, R, view, self.planner.at_rest, self.planner.position, force))
        st = task.status
        if task.episode != self._episode:
            # the task starts a fresh contact episode: older onsets no longer count
            self._episode = task.episode
            self._task_t0 = now
            self._last_est = None
            self._put(("release",), self.to_estimator)
            if task.commanded_onset:
                task.commanded_onset = False
                self._put(("begin", now), self.to_estimator)
            elif task.trigger_phase is not None:
                self._trigger_armed = False
                self._put(("arm", False), self.to_estimator)
        # the task says where its TCP motion along the lever arm is absorbed by the grasp
        absorbed = st.phase in task.absorbed_phases
        if absorbed != (phase_before in task.absorbed_phases):
            self._put(("arc", absorbed), self.to_estimator)
        touching = st.phase in task.touching_phases
        if touching != (phase_before in task.touching_phases):
            self._put(("hold_bias", touching), self.to_estimator)
        if motion is None:
            if st.state == "done":
                self._end_task("done", result=st.result)
            elif st.state == "failed":
                self._end_task("failed", error=st.error)
            return self._brake_step()
        self._R_hold = motion.R
        self._w_ff = np.zeros(3) if motion.w is None else motion.w
        cap = task.speed if motion.max_speed is None else motion.max_speed
        if cap != self._speed_cap:
            self._speed_cap = cap
            self.planner.set_speed(cap)
        lag = float(np.linalg.norm(self.planner.position - p))
        if lag > self.p.max_tracking_error_m:
            # the arm is not following (a joint at its limit, an unreachable target, a collision)
            self._protective_stop("tracking", f"TCP {lag * 1e3:.1f} mm from its planned position "
                                              f"(limit {self.p.max_tracking_error_m * 1e3:.0f} mm)")
            return self._brake_step()
        if np.any(motion.p < self.p.workspace_min) or np.any(motion.p > self.p.workspace_max):
            self._protective_stop("workspace", f"target {np.round(motion.p, 4).tolist()} leaves the workspace box")
            return self._brake_step()
        try:
            return self.planner.step(motion.p, motion.v, motion.min_duration_s)
        except PlannerError as exc:
            self._protective_stop("planner", str(exc))
            return self._brake_step()

    def _brake_step(self) -> tuple[np.ndarray, np.ndarray]:
        self._w_ff = np.zeros(3)
        try:
            p_cmd, v_cmd = self.planner.brake()
        except PlannerError:
            p_cmd, v_cmd = self.planner.position, np.zeros(3)
        if float(np.linalg.norm(v_cmd)) < REST_SPEED_M_S and self.planner.at_rest:
            self._braking = False
            if self.task is None:
                self.mode = "idle"
                for request in self._stop_waiters:
                    self._reply(request, {"ok": True})
                self._stop_waiters.clear()
        return p_cmd, v_cmd

    def _end_task(self, outcome: str, result: dict | None = None, error: str = "") -> None:
        task = self.task
        if task is None:
            return
        self.task = None
        self._braking = True
        self._put(("release",), self.to_estimator)
        if task.touching_phases:
            self._put(("hold_bias", False), self.to_estimator)
        try:
            sim = self._sim_truth(result)
        except Exception:
            # the simulator's truth only annotates the event for tests and benchmarks: a failure
            # there must never cost the task its end event
            log.exception("sim truth for %s failed", task.id)
            sim = None
        if outcome == "done":
            result = dict(result or {})
            if self._task_saturated:
                # said in the result: those samples were left out, the estimate rests on the rest
                result["imu_saturated_samples"] = self._task_saturated
                result["warnings"] = [f"imu_saturated: {self._task_saturated} IMU samples clipped at full scale "
                                      "were left out of the estimate"]
            if sim is not None:
                result["sim"] = sim
            self._event("task_done", task=task.id, verb=task.kind, result=result)
        else:
            extra = {} if sim is None else {"sim": sim}
            partial = task.partial_record() if isinstance(task, MapTask) else None
            if partial is not None:
                # nothing is lost: the points probed so far are fused and written all the same; the
                # directory appears complete or not at all, and `map_written` says when it has
                self._partial_maps.append((task.id, self._write_map(partial)))
                extra["map_pending"] = True
            self._event("task_failed", task=task.id, verb=task.kind, error=error, phase=task.status.phase, **extra)

    def _sim_truth(self, result: dict | None) -> dict | None:
        """The simulated world's truth for benchmarks and tests (None on a real robot)."""
        truth = self.robot.truth() if hasattr(self.robot, "truth") else None
        if truth is None:
            return None
        # the true handle angle, signed about the axis the task rotated about
        axis = (result or {}).get("hinge", result or {}).get("axis")     # None for a point contact
        axis = truth.hinge_axis if axis is None else np.asarray(axis)
        sign = 1.0 if float(np.dot(axis, truth.hinge_axis)) >= 0 else -1.0
        return {"hinge_point": truth.hinge_point.tolist(), "hinge_axis": truth.hinge_axis.tolist(),
                "angle_deg": sign * math.degrees(truth.handle_angle_rad),
                "base_displacement": truth.base_displacement_m, **truth.extra}

    # -- state ----------------------------------------------------------------
    def _publish_state(self, now: float, p, R, v, est) -> None:
        self._seq += 1
        task = None
        if self.task is not None:
            task = {"id": self.task.id, "kind": self.task.kind, "phase": self.task.status.phase,
                    "progress": round(self.task.status.progress, 4)}
        state = {
            "t": now, "seq": self._seq, "mode": "fault" if self.faults and self.task is None and not self._braking else self.mode,
            "tcp": {"p": p.tolist(), "q": matrix_to_quat(R).tolist(), "v": v.tolist()},
            "contact": None if est is None else est.to_json(),
            "task": task,
            "faults": [{"code": c, "message": m} for c, m in self.faults.items()],
            "control": {**self.stats.snapshot(), "planner_fallbacks": self.planner.fallbacks},
        }
        self._put(("state", state))
