"""The tecdard process: builds every component from the config, runs the threads, serves Zenoh."""
from __future__ import annotations

import faulthandler
import gc
import pathlib
import json
import logging
import signal
import sys
import threading
import time

import numpy as np
import zenoh

from tecdard import __version__, verbs
from tecdard.api import commands as C
from tecdard.api.session import JSON, Keys
from tecdard.config import Config, ConfigError
from tecdard.control.geometry import quat_to_matrix
from tecdard.control.pipeline import ContactPipeline
from tecdard.drivers.ring import SampleRing
from tecdard.host import name_os_thread
from tecdard.options import read_options
from tecdard.safejson import show
from tecdard.robots import backends
from tecdard.robots.backends import BackendError
from tecdard.robots.gripper import (ASSUMED, GripperError, GripperParams, build_gripper, force_source,
                                    gripper_kind)
from tecdard.runtime.gripper_worker import GripperWorker
from tecdard.robots.model import READY_Q, ArmModel, UnknownRobotError
from tecdard.runtime.ros2_node import Ros2Params
from tecdard.runtime.control_thread import ControlParams, ControlThread
from tecdard.runtime.intake import QueryIntake
from tecdard.runtime.live_view import LiveView, VizParams
from tecdard.runtime.main_loop import MainLoop, ZenohDoor, status_json
from tecdard.runtime.messages import LatestValue, Outbox, Stop
from tecdard.fleet.episodes import StoreParams
from tecdard.runtime.network import RouterLink, ZenohSettings, renice_zenoh_threads
from tecdard.runtime.realtime import GIL_THREAD_NICE, raise_gil_threads
from tecdard.runtime.recorder import Recorder, RecordParams, config_digest
from tecdard.runtime.rig_options import MAX_TOOL_OFFSET_M, ImuOptions, RobotOptions
from tecdard.runtime.sdnotify import Notifier
from tecdard.runtime.threads import ThreadUsage, WakeStats
from tecdard.runtime.workers import (REST_BATCH_FACTOR, VIEWED_REST_BATCH_FACTOR, EstimatorThread, ProprioFeed,
                                     acquisition_loop, proprio_loop)

log = logging.getLogger("tecdar")

OUTBOX_SIZE = 4096
THREAD_JOIN_S = 0.5
MAIN_POLL_S = 0.005            # the main thread looks at the query ring and the replies at least this often,
MAIN_IDLE_POLL_S = 0.02        # or, at rest (no task, no query for MAIN_BUSY_S), this often: the control tick's
MAIN_BUSY_S = 2.0              # state wakes it then anyway, and a first query waits at most 20 ms more
SHUTDOWN_GRACE_S = 3.0         # on SIGTERM: this long for the arm to stop, a map and a recording to be written
RECORDER_JOIN_S = 1.0          # then the recorder's thread this long more (the unit's TimeoutStopSec: 5 s)
GIL_SWITCH_INTERVAL_S = 0.001
IMU_WARM_TIMEOUT_S = 5.0       # READY waits at most this long for the onset detector's warm-up


def _named(name: str, body):
    """A thread body that first names its OS thread (top -H and /proc show which thread is busy)."""
    def run():
        name_os_thread(name)
        body()
    return run


class Daemon:
    """Reads all options in the constructor (so a bad config never half-starts), runs on `run()`.

    The robot backend (robots.backend.RobotBackend) is the robot the threads read and command; it
    names the fingertip's IMU source (drivers.imu_source.ImuSource) for `imu.source`."""

    def __init__(self, cfg: Config, listen: list[str] | None = None):
        robot = cfg.section("robot")
        own = read_options(RobotOptions, robot)
        backend_name = own.backend
        declared = backends.declared(backend_name)      # what it can do, before it is built
        self._read_robot(robot, own, declared.sends_home)
        self.zenoh = ZenohSettings.from_config(cfg.section("zenoh"), listen)
        self.limits = C.Limits.from_config(cfg.section("limits"))
        self.control_params = ControlParams.from_config(cfg.section("control"), self.limits.max_speed)
        if declared.sends_home:
            self._check_home(robot)
        self.services = verbs.services(cfg)
        imu = cfg.section("imu")
        imu_own = read_options(ImuOptions, imu)
        ring_capacity, mount = imu_own.ring_capacity, list(imu_own.imu_in_tcp_quat)
        self.imu_time_offset_s = imu_own.time_offset_s
        self.backend = backends.build(backend_name, backends.BackendContext(cfg, self.model, self.q_home, mount,
                                                                            self.control_params.tick_s))
        self.robot = self.backend
        self.imu = self._imu_source(imu, backend_name)
        # The onset detector is tuned to the data rate of the source in use; a board's changes as its
        # status packets report its own, which the estimator then follows.
        self.pipeline = ContactPipeline.from_config(cfg.section("estimator"), quat_to_matrix(np.array(mount)),
                                                    self.imu.odr_hz)
        if self.pipeline.rate_notice:
            log.warning("%s", self.pipeline.rate_notice)
        self.method = self.pipeline.method
        self.ros2_params = Ros2Params.from_config(cfg.section("ros2"), self.robot_name)
        self.record_params = RecordParams.from_config(cfg.section("record"))
        self.viz_params = VizParams.from_config(cfg.section("viz").section("foxglove"))
        self.store_params = StoreParams.from_config(cfg.section("store"))
        self.gripper_params = GripperParams.from_config(cfg.section("gripper"))
        try:
            self.gripper_kind = gripper_kind(self.gripper_params.backend, backend_name)
        except GripperError as exc:
            raise ConfigError(str(exc)) from None
        self.robot_section = robot
        cfg.check_unused()
        self._build_threads(cfg, backend_name, mount, ring_capacity)
        try:
            self.zenoh_config = self.zenoh.session_config(self.keys, None if self.ros2 is None else
                                                          self.ros2.acl_keys(self._ros2_state() is not None))
        except Exception as exc:            # zenoh.ZError: Zenoh refuses an endpoint
            raise ConfigError(f"zenoh.listen/connect: Zenoh refuses the endpoints "
                              f"({str(exc).splitlines()[0][:200]})") from None
        self._threads: list[threading.Thread] = []

    def _imu_source(self, imu, backend_name: str):
        """The fingertip's source for `imu.source`, one the backend reads (its first by default)."""
        sources = self.backend.imu_sources
        kind = imu.getstr("source", sources[0], max_len=64)
        if kind not in sources:
            raise imu.error("source", f"with robot.backend {backend_name} the fingertip is read through "
                                      f"{' or '.join(sources)}; got {show(kind)}")
        return self.backend.imu_source(kind, imu)

    def _ros2_state(self):
        """The backend's state as the ROS 2 node's topic hands it over (robots.backend.TopicState), or None."""
        topic = self.backend.topic_state
        return topic if topic is not None and topic.door == "ros2" else None

    def _read_robot(self, robot, own: RobotOptions, sends_home: bool) -> None:
        """The `robot` section's own options (`own`, as read): name, arm model and tool, home posture
        (`sends_home`: the backend sends the arm there, so it must be given)."""
        self.robot_name = own.name
        if not self.robot_name or not self.robot_name.replace("_", "").replace("-", "").isalnum() \
                or not self.robot_name.isascii():
            raise robot.error("name", f"{self.robot_name!r} must be ASCII letters, digits, '-' or '_'")
        model_name, urdf, tcp_link = own.model, own.urdf, own.tcp_link
        if tcp_link is not None and urdf is None:
            raise robot.error("tcp_link", "only with robot.urdf (an arm of robot.model has its own flange)")
        tool_offset = list(own.tool_offset)
        if np.linalg.norm(tool_offset) > MAX_TOOL_OFFSET_M:
            raise robot.error("tool_offset", f"{np.linalg.norm(tool_offset):.3g} m from the flange, at most "
                                             f"{MAX_TOOL_OFFSET_M} m")
        tool_quat = list(own.tool_quat)
        try:
            self.model = ArmModel(model_name if urdf is None else f"urdf:{pathlib.Path(urdf).name}", tool_offset,
                                  tool_quat, urdf=urdf, tcp_link=tcp_link)
        except UnknownRobotError as exc:
            raise ConfigError(str(exc)) from None
        # an observed arm is never sent home: its q_home is only the state before the first joint state
        ready = READY_Q.get(model_name, (self.model.q_min + self.model.q_max) / 2) if urdf is None \
            else (self.model.q_min + self.model.q_max) / 2
        self.q_home = np.array(robot.getfloats("q_home", *([] if sends_home else [list(ready)]),
                                               n=self.model.nq))
        outside = np.flatnonzero((self.q_home < self.model.q_min) | (self.q_home > self.model.q_max))
        if outside.size:
            j = int(outside[0])
            raise robot.error("q_home", f"joint {j + 1} at {self.q_home[j]:.3f} rad is outside its limits "
                                        f"[{self.model.q_min[j]:.3f}, {self.model.q_max[j]:.3f}]")

    def _check_home(self, robot) -> None:
        p_home = self.model.fk(self.q_home).translation
        lo, hi = np.array(self.control_params.workspace_min), np.array(self.control_params.workspace_max)
        if np.any(p_home < lo) or np.any(p_home > hi):
            raise robot.error("q_home", f"the home TCP {np.round(p_home, 3).tolist()} m is outside the workspace "
                                        f"box (control.workspace_min/max)")

    def _build_threads(self, cfg: Config, backend_name: str, mount: list, ring_capacity: int) -> None:
        """What the threads share and own: the IMU ring, the outbox, the recorder and the live view, the
        estimator and control threads, and the command intake."""
        self.ring = SampleRing(ring_capacity)
        self.stop_event = threading.Event()
        self.shutdown_requested = threading.Event()
        self.outbox = Outbox(OUTBOX_SIZE)
        self.contact = LatestValue()
        self.notifier = Notifier()
        self.recorder = Recorder(self.record_params, self.outbox.event, {
            "robot": self.robot_name, "backend": backend_name, "model": self.model.name, "version": __version__,
            "config_digest": config_digest(json.dumps(cfg.data, sort_keys=True, default=str)),
            "estimator": self.method, "imu_in_tcp_quat": list(mount), "imu_time_offset_s": self.imu_time_offset_s,
            "plane_normal": self.pipeline.params.plane_normal,
            # where the grip force comes from (robots/gripper.py): a gripper's command, a person's word, or the
            # configured estimator.grip_force_n where no gripper says (recorded, and said so)
            "grip_force": self.pipeline.params.grip_force_n, "grip_force_source": force_source(self.gripper_kind),
            "grip_force_assumed": force_source(self.gripper_kind) == ASSUMED,
            # the transmission eta calibrated for that grip force (estimator.eta_table): the index's eta
            "eta": float(self.pipeline.measure.eta(np.array([self.pipeline.params.grip_force_n]))[0]),
            "fingertip_lag_s_assumed": self.pipeline.params.fingertip_lag_s})
        self.uploader = self._uploader(cfg)
        self.view = LiveView(self.viz_params, quat_to_matrix(np.array(mount)), self.outbox.event) \
            if self.viz_params.enabled else None
        self.ros2 = self._ros2_node()
        if self.ros2 is not None:
            from tecdard.runtime.option_sections import sections
            self.ros2.set_parameters(cfg.data, sections())   # `ros2 param list/get/describe`: the effective config
        taps = (self.recorder,) + tuple(t for t in (self.view, self.ros2) if t is not None)
        # an arm that others drive (read_only) is watched for touches all the time: never at rest
        # at rest, 100 ms batches; 20 ms while a live view shows the stream to a person
        rest_factor = REST_BATCH_FACTOR if self.view is None else VIEWED_REST_BATCH_FACTOR
        self.estimator = EstimatorThread(self.pipeline, self.ring, self.contact, self.outbox, source=self.imu,
                                         taps=taps, rests=self.backend.commands_arm, rest_factor=rest_factor,
                                         commands=self.backend.commands_arm)
        self.control = ControlThread(self.control_params, self.model, self.robot, self.ring, self.contact,
                                     self.estimator.directive, self.outbox, self.q_home, self.robot_name,
                                     self.notifier, self.services,
                                     estimator=self.estimator)
        self.control.on_command = self.recorder.note_command
        self.ring.wake = WakeStats()
        self.threads = ThreadUsage({"control": self.control.stats.wake, "estimator": self.ring.wake})
        self.keys = Keys(self.robot_name)
        self.intake = QueryIntake(self.keys, self.limits, self.control,
                                  lambda: status_json(self.control, self.intake, self.threads), self.zenoh.intake,
                                  record=self.recorder.request,
                                  read_only=None if self.backend.commands_arm else self.backend.read_only_reason)
        if self.ros2 is not None:
            self.ros2.intake = self.intake

    def _ros2_node(self):
        """The ROS 2 node (ros2.enabled, or an arm that ROS 2 drives, whose joint states it reads)."""
        if not (self.ros2_params.enabled or self._ros2_state() is not None):
            return None
        if not self.ros2_params.enabled:
            log.info("robot.backend %s: the ROS 2 node joins whatever ros2.enabled says (it reads the joint states)",
                     self.backend.name)
        from tecdard.runtime.ros2_node import Ros2Node
        try:
            return Ros2Node(self.ros2_params, self.robot_name, None)
        except ImportError as exc:
            raise ConfigError(f"ros2: the ROS 2 node needs rosbags ({exc.name} is not installed: "
                              "pip install 'tecdar[ros2]')") from None

    def _note_event(self, event: dict) -> None:
        """Every published event, for the recorder and the live view (main thread; never blocks)."""
        self.recorder.note_event(event)
        if self.uploader is not None and event.get("kind") == "recording_written":
            self.uploader.submit(event["path"])
        if self.view is not None:
            self.view.note_event(event)

    # -- lifecycle ----------------------------------------------------------
    def request_stop(self, *_args) -> None:
        """SIGTERM/SIGINT: stop the task as `stop` would (a map writes what it has), then exit; a
        second signal exits at once."""
        if self.shutdown_requested.is_set():
            self.stop_event.set()
        self.shutdown_requested.set()

    def _uploader(self, cfg):
        """The `store` section: an uploader thread when it names a store and uploads (docs/fleet.md)."""
        params = self.store_params
        if not params.url or not params.upload:
            return None
        from tecdard.runtime.recorder import OWN_NAME
        from tecdard.runtime.uploader import Uploader
        uploader = Uploader(params, self.record_params.dir, self.robot_name, self.outbox.event,
                            config=getattr(cfg, "source", None), own_name=OWN_NAME,
                            at_rest=lambda: self.control.quiescent())
        self.recorder.may_delete = uploader.may_delete
        return uploader

    def _start_threads(self) -> None:
        self.backend.start()
        # the real board, or (sim-wire) the child's pty, which exists once the child has started
        problem = self.imu.start()
        if problem is not None:
            log.warning("%s", problem)
        # the port is read from the moment it is open: a gripper's activation below takes seconds on a real
        # Robotiq, and a board's stream held in the kernel's buffer meanwhile is read as one late backlog
        # (dropped bytes once the buffer is full; the clock sync's first bins far above the envelope)
        self._start("imu-acquisition", lambda: acquisition_loop(self.imu, self.ring, self.stop_event, self.outbox,
                                                                self.imu_time_offset_s))
        # the robot's states to the estimator: on the link's own reader where the backend has one (a
        # thread fewer to wake for every state), else on a proprioception thread
        feed = ProprioFeed(self.model.clone(), self.estimator.proprio)
        worker = self._gripper_worker()
        feed.gripper = self.control.gripper = worker
        own_reader = self.backend.feed_states(feed)
        specs = [*([] if own_reader else [("proprioception", lambda: proprio_loop(self.robot, feed, self.stop_event))]),
                 ("estimator", lambda: self.estimator.run(self.stop_event)),
                 ("recorder", lambda: self.recorder.run(self.stop_event)),
                 *([("uploader", lambda: self.uploader.run(self.stop_event))] if self.uploader is not None else []),
                 *([("viz", lambda: self.view.run(self.stop_event))] if self.view is not None else []),
                 *([("gripper", lambda: worker.run(self.stop_event))] if worker is not None else []),
                 ("control", lambda: self.control.run(self.stop_event))]
        for name, body in specs:
            self._start(name, body)

    def _start(self, name: str, body) -> None:
        th = threading.Thread(target=_named(name, body), name=name, daemon=True)
        th.start()
        self._threads.append(th)

    def _gripper_worker(self) -> GripperWorker | None:
        """The configured gripper, reached once the arm's backend has started (a Franka Hand's connection is the
        arm link's), on a thread of its own; BackendError (one line) when it cannot be reached."""
        try:
            gripper = build_gripper(self.gripper_params, self.gripper_kind, self.backend, self.robot_section)
        except GripperError as exc:
            raise BackendError(str(exc)) from None
        if gripper is None:
            return None
        log.info("gripper: %s, %s", gripper.kind, gripper.state().to_json(gripper.kind))
        return GripperWorker(gripper, self.gripper_params, self.outbox, self.control.replies)

    def _shutdown(self) -> None:
        """Stop motion first, then the threads; each step guarded so one failure skips nothing."""
        self.stop_event.set()
        self.notifier.stopping()
        for th in self._threads:
            try:
                th.join(RECORDER_JOIN_S if th.name == "recorder" else THREAD_JOIN_S)
            except Exception:
                log.exception("joining %s", th.name)
        for step in (self.robot.hold, self.backend.close, self.imu.close):
            try:
                step()
            except Exception:
                log.exception("shutdown step %s failed", getattr(step, "__name__", step))
        if not any(th.name == "control" and th.is_alive() for th in self._threads):
            # the control thread releases the planner's Ruckig objects as it ends; one that never
            # started (a failed start) leaves that to here, or nanobind reports them at exit
            self.control.runner.planner.release()

    def run(self) -> int:
        # The acquisition and sim-link threads block on I/O and need the GIL back at once when
        # data come; with the estimator computing, each hand-over waits up to a switch interval
        # (5 ms by default). 1 ms keeps IMU chunks from queueing behind the estimator. (0.25 ms
        # cut the UR path's tick lateness a little, but starved the simulated firmware board's
        # stream at start: imu_stale in 2 of 3 runs of tests/test_firmware.py's rotate.)
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        # A daemon that hangs says where: systemd's watchdog and a stop that times out
        # (TimeoutStopFailureMode=abort) send SIGABRT, and every thread's stack goes to stderr (the journal)
        faulthandler.enable(all_threads=True)
        signal.signal(signal.SIGINT, self.request_stop)
        signal.signal(signal.SIGTERM, self.request_stop)
        with zenoh.open(self.zenoh_config) as session:
            pubs = tuple(session.declare_publisher(key, encoding=JSON)
                         for key in (self.keys.state, self.keys.contact, self.keys.events))
            self.intake.declare(session)
            if self.ros2 is not None:
                state = self._ros2_state()
                self.ros2.declare(session, None if state is None else state.take,
                                  0.0 if state is None else state.min_period_s,
                                  None if state is None else state.take_wrench)
            # Everything built so far lives as long as the daemon. A full garbage collection walks
            # every tracked object with the GIL held: with the estimator's compiled loops (numba,
            # llvmlite) loaded that is ~116 000 objects and a 57 ms stall of every thread, several
            # control ticks and IMU chunks. Frozen, they are never walked again (under 0.1 ms).
            gc.collect()
            gc.freeze()
            token = None
            try:
                self._start_threads()
                renice_zenoh_threads()
                if self.control_params.rt_priority is not None:
                    problem = raise_gil_threads()
                    (log.warning if problem else log.info)(
                        "the threads the control tick waits on for the GIL %s", f"stay at nice 0: {problem}"
                        if problem else f"run at nice {GIL_THREAD_NICE}")
                self._wait_ready()
                token = session.liveliness().declare_token(self.keys.alive)
                self.notifier.notify("READY=1")
                log.info("tecdard ready: robot %s (%s), %s", self.robot_name, self.model.name, self.zenoh.where())
                fleet_problem = self.zenoh.fleet_problem(self.robot_name)
                if fleet_problem:
                    log.warning("%s", fleet_problem)
                self._serve(pubs, RouterLink(session, self.zenoh.connect) if self.zenoh.mode == "client" else None)
            finally:
                # also when a start fails (a backend that cannot connect): what did start is stopped
                self.intake.undeclare()
                if self.ros2 is not None:
                    self.ros2.undeclare()
                self._shutdown()
                if token is not None:
                    token.undeclare()
        log.info("tecdard stopped")
        return 0

    def _wait_ready(self) -> None:
        """Ready once a contact can be detected: the onset detector needs its warm-up of IMU data at rest
        (estimator.onset.warmup_s). A task sent before that would probe blind for its first tens of
        milliseconds and localise from a late onset."""
        if not self.control.first_tick.wait(2.0):
            log.error("control thread did not tick within 2 s")
        warm_by = time.monotonic() + IMU_WARM_TIMEOUT_S
        while not self.estimator.warm.wait(0.05) and not self.shutdown_requested.is_set():
            if time.monotonic() > warm_by:
                log.warning("the IMU has not streamed its onset warm-up within %.0f s; contacts are not "
                            "detected until it has", IMU_WARM_TIMEOUT_S)
                return

    def _serve(self, pubs, router_link=None) -> None:
        """The main thread's loop (MainLoop's passes) until the daemon stops; an orderly stop on a signal.
        `router_link` (network.RouterLink, a client-mode daemon's): a lost router is the control
        thread's robot_link fault while it lasts."""
        doors = (ZenohDoor(self.intake, *pubs),) + ((self.ros2,) if self.ros2 is not None else ())
        main = MainLoop(self.intake, self.control, self.outbox, doors, annotate=self.backend.annotate,
                        on_event=self._note_event)
        shutdown_by = None
        cut = None
        while not self.stop_event.is_set():
            now = time.monotonic()
            self.threads.sample(now)
            problem = router_link.problem(now) if router_link is not None else None
            if problem != cut:
                cut = problem
                (log.warning if cut else log.info)("%s", cut or "the Zenoh router connects the daemon again")
                self.control.network_fault.set(cut)
            main.serve_commands(now)
            if self.shutdown_requested.is_set():
                if shutdown_by is None:
                    log.info("shutting down: stopping the task and the arm first")
                    self.notifier.stopping()
                    self.control.request_stop(Stop(None, "daemon shutting down"))
                    # a capture is closed and written now, while the arm stops, not after it
                    self.recorder.close_capture("daemon stopping")
                    shutdown_by = now + SHUTDOWN_GRACE_S
                elif (self.control.quiescent() and self.recorder.idle) or now > shutdown_by:
                    if not self.control.quiescent():
                        log.warning("shutting down before the arm came to rest or the map was written "
                                    "(%.1f s grace)", SHUTDOWN_GRACE_S)
                    if not self.recorder.idle:
                        log.warning("shutting down while a recording is still being written (%.1f s grace; "
                                    "%.1f s more are given to it)", SHUTDOWN_GRACE_S, RECORDER_JOIN_S)
                    break
            at_rest = now - main.active_at > MAIN_BUSY_S and self.control.quiescent()
            main.publish_telemetry(MAIN_IDLE_POLL_S if at_rest else MAIN_POLL_S)
