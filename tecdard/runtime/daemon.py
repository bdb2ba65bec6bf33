"""The tecdard process: builds every component from the config, runs the threads, serves Zenoh."""
from __future__ import annotations

import gc
import json
import logging
import os
import pathlib
import queue
import signal
import sys
import threading
import time

import numpy as np
import zenoh

from tecdard.control.geometry import quat_to_matrix
from tecdard.drivers.ring import SampleRing
from tecdard.drivers.serial_imu import PortError, SerialImuSource, SerialParams
from tecdard.robots import backends
from tecdard.robots.model import ArmModel, UnknownRobotError
from tecdard.api import commands as C
from tecdard.config import Config, ConfigError
from tecdard.control.pipeline import ContactPipeline
from tecdard.runtime.intake import IntakeParams, QueryIntake
from tecdard.runtime.messages import Stop
from tecdard import __version__
from tecdard.verbs.map.files import MapSettings
from tecdard.runtime.recorder import Recorder, RecordParams, config_digest
from tecdard.runtime.live_view import LiveView, VizParams
from tecdard.runtime.control_thread import ControlParams, ControlThread
from tecdard.runtime.messages import LatestValue
from tecdard.runtime.sdnotify import Notifier
from tecdard.runtime.workers import EstimatorThread, acquisition_loop, proprio_loop
from tecdard.safejson import show
from tecdard.api.session import (DAEMON_MAX_MESSAGE_BYTES, JSON, Keys, TlsFiles, access_control, dumps,
                                 endpoint_problem, session_config)

log = logging.getLogger("tecdar")

OUTBOX_SIZE = 4096
THREAD_JOIN_S = 0.5
MAIN_POLL_S = 0.005            # the main thread looks at the query ring and the replies at least this often
TELEMETRY_PER_PASS = 64        # state, contact and event messages published per pass, then queries again
SHUTDOWN_GRACE_S = 3.0         # on SIGTERM: this long for the arm to stop and a map to be written (unit: 5 s)
GIL_SWITCH_INTERVAL_S = 0.001
IMU_WARM_TIMEOUT_S = 5.0       # READY waits at most this long for the onset detector's warm-up
MAX_ROBOT_NAME_CHARS = 64      # the name is a chunk of every key expression
MAX_ENDPOINT_CHARS = 256
MAX_TOOL_OFFSET_M = 0.5        # flange -> TCP; anything longer is a typo (mm for m), not a tool
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7507"


ZENOH_THREAD_NICE = 5          # Zenoh's network threads run this much nicer than the daemon's own


def _renice_zenoh_threads() -> None:
    """Zenoh's network threads (rx-*, tx-*, net-*, acc-*, app-*: Rust, outside the GIL) at a lower
    CPU priority than the daemon's own threads. Under contention (a flood of queries decoded on
    them, a loaded host) the control loop, the IMU path and the estimator are served first; a
    process may always lower its own threads' priority. Best effort: Linux only, failures ignored."""
    for task in pathlib.Path("/proc/self/task").glob("*"):
        try:
            name = (task / "comm").read_text().strip()
            if name.split("-")[0] in ("rx", "tx", "net", "acc", "app"):
                os.setpriority(os.PRIO_PROCESS, int(task.name), os.getpriority(os.PRIO_PROCESS, 0) + ZENOH_THREAD_NICE)
        except (OSError, ValueError):
            pass


def _security(zc, endpoints: list[str]) -> tuple[TlsFiles | None, list[str]]:
    """zenoh.tls (mutual TLS: ca, cert, key) and zenoh.commanders (certificate common names that may
    send commands), checked: the files readable, every endpoint tls/ when TLS is on (a tcp/ beside it
    would let anyone in unauthenticated), and commanders only with TLS (names come from certificates)."""
    tls = None
    if zc.has("tls"):
        sec = zc.section("tls")
        files = {}
        for key in ("ca", "cert", "key"):
            path = sec.getstr(key)
            try:
                with open(path, "rb") as fh:
                    if b"-----BEGIN" not in fh.read(64 * 1024):
                        raise ConfigError(f"zenoh.tls.{key}: {show(path)} is not a PEM file")
            except OSError as exc:
                raise ConfigError(f"zenoh.tls.{key}: cannot read {show(path)} ({exc.strerror})") from None
            files[key] = path
        tls = TlsFiles(**files)
        plain = [ep for ep in endpoints if not ep.startswith("tls/")]
        if plain:
            raise ConfigError(f"zenoh.listen/connect: {show(plain[0])} is not a tls/ endpoint; with zenoh.tls every "
                              "endpoint must be, or unauthenticated peers get in beside it")
    elif any(ep.startswith("tls/") for ep in endpoints):
        raise ConfigError("zenoh.tls: a tls/ endpoint needs zenoh.tls (ca, cert, key)")
    commanders = zc.getstrlist("commanders", [], max_len=256, max_items=64)
    if commanders and tls is None:
        raise ConfigError("zenoh.commanders: needs zenoh.tls (the names are certificates' common names)")
    if zc.has("commanders") and not commanders:
        raise ConfigError("zenoh.commanders: an empty list would let nobody command; leave it out to let every "
                          "authenticated peer command")
    return tls, commanders


class Daemon:
    """Reads all options in the constructor (so a bad config never half-starts), runs on `run()`."""

    def __init__(self, cfg: Config, listen: list[str] | None = None):
        robot = cfg.section("robot")
        self.robot_name = robot.getstr("name", "sim", max_len=MAX_ROBOT_NAME_CHARS)
        if not self.robot_name or not self.robot_name.replace("_", "").replace("-", "").isalnum() \
                or not self.robot_name.isascii():
            raise ConfigError(f"robot.name: {self.robot_name!r} must be ASCII letters, digits, '-' or '_'")
        model_name = robot.getstr("model", "panda", max_len=64)
        backend_name = robot.getstr("backend", "sim", choices=backends.names())
        try:
            tool_offset = robot.getvec3("tool_offset", [0.0, 0.0, 0.0])
            if np.linalg.norm(tool_offset) > MAX_TOOL_OFFSET_M:
                raise ConfigError(f"robot.tool_offset: {np.linalg.norm(tool_offset):.3g} m from the flange, "
                                  f"at most {MAX_TOOL_OFFSET_M} m")
            tool_quat = robot.getquat("tool_quat", [0.0, 0.0, 0.0, 1.0])
            self.model = ArmModel(model_name, tool_offset, tool_quat)
        except UnknownRobotError as exc:
            raise ConfigError(str(exc)) from None
        self.q_home = np.array(robot.getfloats("q_home", n=self.model.nq))
        outside = np.flatnonzero((self.q_home < self.model.q_min) | (self.q_home > self.model.q_max))
        if outside.size:
            j = int(outside[0])
            raise ConfigError(f"robot.q_home: joint {j + 1} at {self.q_home[j]:.3f} rad is outside its limits "
                              f"[{self.model.q_min[j]:.3f}, {self.model.q_max[j]:.3f}]")

        zc = cfg.section("zenoh")
        # peer (default): listens for clients itself, and may also connect to a router on the host;
        # client: reaches everything through the routers in zenoh.connect and listens on nothing
        self.zenoh_mode = zc.getstr("mode", "peer", choices=("peer", "client"))
        configured = zc.getstrlist("listen", [DEFAULT_ENDPOINT] if self.zenoh_mode == "peer" else [],
                                   max_len=MAX_ENDPOINT_CHARS, max_items=16)
        self.listen = listen if listen is not None else configured
        self.connect = zc.getstrlist("connect", [], max_len=MAX_ENDPOINT_CHARS, max_items=16)
        self.multicast = zc.getbool("multicast_scouting", False)
        if self.zenoh_mode == "client" and self.listen:
            raise ConfigError("zenoh.listen: a Zenoh client listens on nothing; leave it out with mode: client")
        if self.zenoh_mode == "client" and not self.connect:
            raise ConfigError("zenoh.connect: mode client needs a router's endpoint to connect to")
        if not self.listen and not self.connect:
            raise ConfigError("zenoh.listen: empty, and nothing in zenoh.connect: no client could reach the daemon")
        for key, endpoints in (("listen", self.listen), ("connect", self.connect)):
            for ep in endpoints:
                problem = endpoint_problem(ep)
                if problem:
                    raise ConfigError(f"zenoh.{key}: {show(ep)}: {problem}")
        self.tls, commanders = _security(zc, self.listen + self.connect)
        intake_params = IntakeParams.from_config(zc)

        self.limits = C.Limits.from_config(cfg.section("limits"))
        self.control_params = ControlParams.from_config(cfg.section("control"), self.limits.max_speed)
        p_home = self.model.fk(self.q_home).translation
        lo, hi = np.array(self.control_params.workspace_min), np.array(self.control_params.workspace_max)
        if np.any(p_home < lo) or np.any(p_home > hi):
            raise ConfigError(f"robot.q_home: the home TCP {np.round(p_home, 3).tolist()} m is outside the "
                              f"workspace box (control.workspace_min/max)")
        self.map_settings = MapSettings.from_config(cfg.section("map"))

        imu = cfg.section("imu")
        self.imu_source = imu.getstr("source", "sim", choices=("sim", "sim-wire", "serial"))
        serial_params = SerialParams.from_config(imu.section("serial")) if self.imu_source == "serial" else None
        ring_capacity = imu.getint("ring_capacity", 65536, minval=1024, maxval=1 << 22)
        mount = imu.getquat("imu_in_tcp_quat", [0.0, 0.0, 0.0, 1.0])

        self.backend = backends.build(backend_name, backends.BackendContext(cfg, self.model, self.q_home,
                                                                            self.imu_source, mount,
                                                                            self.control_params.tick_s))
        if self.backend.serial_params is not None:
            serial_params = self.backend.serial_params          # sim-wire: the simulated board's pty
        # The onset detector is tuned to the data rate of the source in use: the board's (its serial
        # config until its first status packet reports its own, which the estimator then follows),
        # or the simulated one's.
        source_odr_hz = float(serial_params.odr_hz) if serial_params is not None else self.backend.imu_odr_hz
        self.pipeline = ContactPipeline.from_config(cfg.section("estimator"), quat_to_matrix(np.array(mount)), source_odr_hz)
        self.method = self.pipeline.method
        self.record_params = RecordParams.from_config(cfg.section("record"))
        self.viz_params = VizParams.from_config(cfg.section("viz").section("foxglove"))
        cfg.check_unused()

        self.ring = SampleRing(ring_capacity)
        self.robot = self.backend.robot
        self.imu = SerialImuSource(serial_params) if serial_params is not None else self.backend.imu
        self.stop_event = threading.Event()
        self.shutdown_requested = threading.Event()
        self.outbox: queue.Queue = queue.Queue(maxsize=OUTBOX_SIZE)
        self.contact = LatestValue()
        self.notifier = Notifier()
        self.recorder = Recorder(self.record_params, self._emit, {
            "robot": self.robot_name, "backend": backend_name, "model": self.model.name, "version": __version__,
            "config_digest": config_digest(json.dumps(cfg.data, sort_keys=True, default=str)),
            "estimator": self.method, "imu_in_tcp_quat": list(mount),
            "plane_normal": self.pipeline.params.plane_normal})
        self.view = LiveView(self.viz_params, quat_to_matrix(np.array(mount)), self._emit) \
            if self.viz_params.enabled else None
        self.estimator = EstimatorThread(self.pipeline, self.ring, self.contact, self.outbox,
                                         saturation=lambda: self.imu.saturation, odr_hz=lambda: self.imu.odr_hz,
                                         taps=(self.recorder,) + ((self.view,) if self.view is not None else ()))
        self.control = ControlThread(self.control_params, self.model, self.robot, self.ring, self.contact,
                                     self.estimator.directive, self.outbox, self.q_home, self.robot_name, self.notifier,
                                     self.map_settings, imu_saturated_since=lambda: self.estimator.saturated_since)
        self.keys = Keys(self.robot_name)
        self.intake = QueryIntake(self.keys, self.limits, self.control, lambda: status_json(self.control),
                                  intake_params, record=self.recorder.request)
        try:
            acl = access_control(self.keys, commanders) if commanders else None
            self.zenoh_config = session_config(self.listen, self.connect, self.multicast, DAEMON_MAX_MESSAGE_BYTES,
                                               tls=self.tls, acl=acl, mode=self.zenoh_mode)
        except Exception as exc:            # zenoh.ZError: Zenoh refuses an endpoint
            raise ConfigError(f"zenoh.listen/connect: Zenoh refuses the endpoints ({str(exc).splitlines()[0][:200]})") from None
        self._threads: list[threading.Thread] = []

    def _note_event(self, event: dict) -> None:
        """Every published event, for the recorder and the live view (main thread; never blocks)."""
        self.recorder.note_event(event)
        if self.view is not None:
            self.view.note_event(event)

    def _emit(self, kind: str, **fields) -> None:
        """An event from a thread that is not the control thread's (the recorder's)."""
        try:
            self.outbox.put_nowait(("event", {"t": time.monotonic(), "kind": kind, **fields}))
        except queue.Full:
            log.warning("event %s dropped: the outbox is full", kind)

    def _where(self) -> str:
        parts = [f"listening on {', '.join(self.listen)}"] if self.listen else []
        if self.connect:
            parts.append(f"connecting to {', '.join(self.connect)}")
        return f"Zenoh {self.zenoh_mode}, " + " and ".join(parts)

    # -- lifecycle ----------------------------------------------------------
    def request_stop(self, *_args) -> None:
        """SIGTERM/SIGINT: stop the task as `stop` would (a map writes what it has), then exit; a
        second signal exits at once."""
        if self.shutdown_requested.is_set():
            self.stop_event.set()
        self.shutdown_requested.set()

    def _start_threads(self) -> None:
        self.backend.start()
        if isinstance(self.imu, SerialImuSource):
            # the real board, or (sim-wire) the child's pty, which exists once the child has started
            try:
                self.imu.open()
            except PortError as exc:
                log.warning("%s; retrying in the background", exc)
                self.imu.mark_lost(str(exc))
        proprio_model = self.model.clone()      # the proprioception thread's own pinocchio Data
        specs = [("imu-acquisition", lambda: acquisition_loop(self.imu, self.ring, self.stop_event, self.outbox)),
                 ("proprioception", lambda: proprio_loop(self.robot, proprio_model, self.estimator.proprio,
                                                         self.stop_event)),
                 ("estimator", lambda: self.estimator.run(self.stop_event)),
                 ("recorder", lambda: self.recorder.run(self.stop_event)),
                 *([("viz", lambda: self.view.run(self.stop_event))] if self.view is not None else []),
                 ("control", lambda: self.control.run(self.stop_event))]
        for name, body in specs:
            th = threading.Thread(target=body, name=name, daemon=True)
            th.start()
            self._threads.append(th)

    def _shutdown(self) -> None:
        """Stop motion first, then the threads; each step guarded so one failure skips nothing."""
        self.stop_event.set()
        self.notifier.notify("STOPPING=1")
        for th in self._threads:
            try:
                th.join(THREAD_JOIN_S)
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
        # (5 ms by default). 1 ms keeps IMU chunks from queueing behind the estimator.
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        signal.signal(signal.SIGINT, self.request_stop)
        signal.signal(signal.SIGTERM, self.request_stop)
        with zenoh.open(self.zenoh_config) as session:
            pub_state = session.declare_publisher(self.keys.state, encoding=JSON)
            pub_contact = session.declare_publisher(self.keys.contact, encoding=JSON)
            pub_events = session.declare_publisher(self.keys.events, encoding=JSON)
            self.intake.declare(session)
            # Everything built so far lives as long as the daemon. A full garbage collection walks
            # every tracked object with the GIL held: with the estimator's compiled loops (numba,
            # llvmlite) loaded that is ~116 000 objects and a 57 ms stall of every thread, several
            # control ticks and IMU chunks. Frozen, they are never walked again (under 0.1 ms).
            gc.collect()
            gc.freeze()
            token = None
            try:
                self._start_threads()
                _renice_zenoh_threads()
                if not self.control.first_tick.wait(2.0):
                    log.error("control thread did not tick within 2 s")
                # Alive and READY once a contact can be detected: the onset detector needs its warm-up of
                # IMU data at rest (estimator.onset.warmup_s). A task sent before that would probe blind
                # for its first tens of milliseconds and localise from a late onset.
                warm_by = time.monotonic() + IMU_WARM_TIMEOUT_S
                while not self.estimator.warm.wait(0.05) and not self.shutdown_requested.is_set():
                    if time.monotonic() > warm_by:
                        log.warning("the IMU has not streamed its onset warm-up within %.0f s; contacts are not "
                                    "detected until it has", IMU_WARM_TIMEOUT_S)
                        break
                token = session.liveliness().declare_token(self.keys.alive)
                self.notifier.notify("READY=1")
                log.info("tecdard ready: robot %s (%s), %s", self.robot_name, self.model.name, self._where())
                self._serve(pub_state, pub_contact, pub_events)
            finally:
                # also when a start fails (a backend that cannot connect): what did start is stopped
                self.intake.undeclare()
                self._shutdown()
                if token is not None:
                    token.undeclare()
        log.info("tecdard stopped")
        return 0

    def _serve(self, pub_state, pub_contact, pub_events) -> None:
        """The main thread's loop (MainLoop's passes) until the daemon stops; an orderly stop on a signal."""
        main = MainLoop(self.intake, self.control, self.outbox, pub_state, pub_contact, pub_events,
                        annotate=getattr(self.backend, "annotate", None), on_event=self._note_event)
        shutdown_by = None
        while not self.stop_event.is_set():
            now = time.monotonic()
            main.serve_commands(now)
            if self.shutdown_requested.is_set():
                if shutdown_by is None:
                    log.info("shutting down: stopping the task and the arm first")
                    self.control.request_stop(Stop(None, "daemon shutting down"))
                    shutdown_by = now + SHUTDOWN_GRACE_S
                elif self.control.quiescent() or now > shutdown_by:
                    if not self.control.quiescent():
                        log.warning("shutting down before the arm came to rest or the map was written "
                                    "(%.1f s grace)", SHUTDOWN_GRACE_S)
                    break
            main.publish_telemetry(MAIN_POLL_S)


def status_json(control) -> str | None:
    """`status`: the control thread's newest state (at most a tick old), not the newest published
    one, which can wait behind other telemetry while replies go first."""
    state = control.latest_state.get()
    return None if state is None else dumps(state)


class MainLoop:
    """One pass of the main thread: the control thread's replies first, then the queued queries
    (bounded per ring), then at most TELEMETRY_PER_PASS telemetry messages. However much telemetry
    waits, a command's reply waits at most one pass behind it."""

    def __init__(self, intake: QueryIntake, control, outbox: queue.Queue, pub_state, pub_contact, pub_events,
                 annotate=None, on_event=None):
        """`annotate(event) -> event`: the backend's additions to events (the simulator's truth on
        a task's end), applied here on the main thread, never on the control tick. `on_event(event)`
        sees every event published (the recorder's)."""
        self.intake, self.control, self.outbox = intake, control, outbox
        self.pub = {"state": pub_state, "contact": pub_contact, "event": pub_events}
        self.annotate = annotate
        self.on_event = on_event

    def serve_commands(self, now: float) -> None:
        while True:
            try:
                self.intake.deliver(self.control.replies.get_nowait())
            except queue.Empty:
                break
        self.intake.poll(now)

    def publish_telemetry(self, wait_s: float) -> int:
        """Publish up to TELEMETRY_PER_PASS queued messages, waiting up to wait_s for the first."""
        try:
            msg = self.outbox.get(timeout=wait_s) if wait_s > 0 else self.outbox.get_nowait()
        except queue.Empty:
            return 0
        for n in range(1, TELEMETRY_PER_PASS + 1):
            kind, body = msg[0], msg[1]
            if kind == "event" and self.annotate is not None:
                body = self._annotated(body)
            text = dumps(body)
            if kind == "event":
                log.info("event %s", text)
                if self.on_event is not None:
                    self.on_event(body)
            self.pub[kind].put(text)          # the threads put only these three kinds
            if n == TELEMETRY_PER_PASS:
                return n
            try:
                msg = self.outbox.get_nowait()
            except queue.Empty:
                return n
        return TELEMETRY_PER_PASS

    def _annotated(self, event: dict) -> dict:
        try:
            return self.annotate(event)
        except Exception:
            # an annotation is for tests and benchmarks: a failure never costs the event itself
            log.exception("annotating a %s event failed", event.get("kind"))
            return event
