"""Robot backend interfaces: reading state apart from commanding, in the manner of ur_rtde."""
from __future__ import annotations

import multiprocessing
import threading
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pinocchio as pin

from tecdard.robots.backends import BackendError


@dataclass
class JointState:
    """Proprioception as a robot reports it: joint positions and rates on the daemon's clock."""
    t: float                 # monotonic time of the measurement, s
    q: np.ndarray            # rad
    qd: np.ndarray           # rad/s
    seq: int = 0             # increments with every new measurement
    tcp_twist: np.ndarray | None = None   # [v; w] world-aligned, m/s and rad/s, when the robot reports it
    tcp_force: np.ndarray | None = None   # external force on the TCP, world, N, when the robot estimates it
    tcp_pose: np.ndarray | None = None    # oMtcp (4 x 4, world) as the robot reports it, from its own calibrated
                                          # kinematics and TCP setting; None: the daemon's FK of q
    grip_force: float | None = None       # the gripper's grasp force, N, where the robot reads one (eta's
                                          # schedule); None: estimator.grip_force_n, the configured constant


def joint_rates(qd, nq: int) -> np.ndarray:
    """A joint velocity command as an array, or ValueError naming what is wrong with it."""
    qd = np.asarray(qd, dtype=float)
    if qd.shape != (nq,) or not np.all(np.isfinite(qd)):
        raise ValueError(f"qd: expected {nq} finite joint rates")
    return qd


class StateSlot:
    """The newest JointState of a robot link, between the thread that receives states and the
    threads that read them: `publish` replaces it and wakes the waiters; `close` (the link has gone)
    wakes them for good, and reads then raise `error()`."""

    def __init__(self, error):
        self._error = error                  # () -> the exception to raise once closed or before a state
        self._state: JointState | None = None
        self._cond = threading.Condition()
        self.closed = threading.Event()

    def publish(self, js: JointState) -> None:
        with self._cond:
            self._state = js
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed.set()
            self._cond.notify_all()

    def read(self) -> JointState:
        if self._state is None:
            raise self._error()
        return self._state

    def wait(self, seq: int, timeout: float) -> JointState:
        """The newest state once its seq differs from `seq`, or after `timeout` s."""
        with self._cond:
            self._cond.wait_for(lambda: self.closed.is_set() or (self._state is not None and self._state.seq != seq),
                                timeout)
        if self.closed.is_set():
            raise self._error()
        return self.read()


CHILD_STOP_S = 2.0      # a robot link's child process is waited for this long, then terminated


def kill_child(proc) -> None:
    """Terminate a child process that is still alive, and wait for it."""
    if proc is not None and proc.is_alive():
        proc.terminate()
        proc.join(CHILD_STOP_S)


def end_child(proc, conns) -> None:
    """A child process that has been asked to stop: wait for it, terminate it if it does not, and
    close the parent's ends of its pipes (a link that reconnects makes new ones)."""
    proc.join(CHILD_STOP_S)
    kill_child(proc)
    for conn in conns:
        conn.close()


class RobotReceive(Protocol):
    """Reading side: latest proprioception."""

    def read_state(self) -> JointState: ...

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s (every new
        measurement, for the estimator, at the robot's own rate)."""
        ...


class RobotControl(Protocol):
    """Commanding side: joint velocity streaming, and a hold."""

    def command_joint_velocity(self, qd: np.ndarray) -> None: ...

    def hold(self) -> None: ...


class ChildLink:
    """What a robot link whose client runs in a child process (robots.ur_link, robots.franka_link)
    shares: its command pipe, the newest state (`_states`, a StateSlot) and the child's end.
    Subclasses set `error` (their BackendError) and `settings` (with `host`), and start the child."""

    error = BackendError

    def __init__(self, settings):
        self.settings = settings
        self._proc = None
        self._cmd = self._state_rx = None
        self._send_lock = threading.Lock()
        self._states = StateSlot(lambda: self.error(self.fault or f"no state from {self.settings.host} yet"))
        self.exited = self._states.closed
        self.fault: str | None = None               # the link's own fault (lost), or None

    def _spawn(self, target, name: str) -> None:
        """Start the child `target(settings, cmd_rx, state_tx)` with a command pipe in and a state pipe out."""
        ctx = multiprocessing.get_context("spawn")
        cmd_rx, self._cmd = ctx.Pipe(duplex=False)
        self._state_rx, state_tx = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=target, args=(self.settings, cmd_rx, state_tx), name=name, daemon=True)
        self._proc.start()
        cmd_rx.close()
        state_tx.close()

    def stop(self) -> None:
        if self._proc is None:
            return
        self._send(("close",), quiet=True)
        end_child(self._proc, (self._cmd, self._state_rx))
        self._proc = None

    def _send(self, msg: tuple, quiet: bool = False) -> None:
        try:
            with self._send_lock:
                self._cmd.send(msg)
        except (OSError, ValueError, AttributeError, BrokenPipeError):
            if not quiet:
                raise self.error(f"the link to {self.settings.host} is not running") from None

    def read_state(self) -> JointState:
        return self._states.read()

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s; the link's error
        once it has gone."""
        return self._states.wait(seq, timeout)


def rig_section(ctx, backend: str, models: tuple[str, ...], arm: str, host_is: str):
    """The `robot.<backend>` section of a real arm's backend, after the checks every such backend
    makes: robot.model is one of `models`, the fingertip board is read over serial, and the
    section names a host (ConfigError naming the key otherwise)."""
    from tecdard.config import ConfigError
    if ctx.model.name not in models:
        raise ConfigError(f"robot.model: {ctx.model.name!r} is no {arm} arm; with robot.backend {backend} use one of "
                          f"{', '.join(models)}")
    if ctx.imu_source != "serial":
        raise ConfigError(f"imu.source: with robot.backend {backend} the fingertip board is read over serial; "
                          "set imu.source: serial")
    section = ctx.cfg.section("robot").section(backend)
    if not section.has("host"):
        raise ConfigError(f"robot.{backend}.host: required with robot.backend {backend} ({host_is})")
    return section


RECONNECT_S = (0.5, 1.0, 2.0, 4.0)      # back-off between reconnect attempts, then the last one repeated


FK_CHECK_M = 0.003         # our FK and the robot's own TCP pose further apart than this: said at start
FK_CHECK_RAD = 0.0175      # ... or turned by more than this (1 degree)


class LinkBackend:
    """Receive and control, as any backend, for a backend that reaches its robot through a
    ChildLink (`self.link`, replaced when it reconnects; `self._stop` set on close). A link that is
    down answers with its last state and takes no command: its fault has stopped the task already.
    The fingertip board is read by the serial driver (imu.source: serial)."""

    imu = None
    serial_params = None
    imu_odr_hz = None
    link: ChildLink
    settings: object
    model: object                      # robots.model.ArmModel
    log: object                        # the backend's logger
    _stop: threading.Event

    def _attach(self, ctx, link: ChildLink) -> None:
        """What every link backend holds once its settings are read: the arm model and the link
        (not yet started); the backend is its own robot."""
        self.nq = ctx.model.nq
        self.model = ctx.model
        self.link = link
        self.robot = self
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None

    def _say_fk_offset(self, q, pose: np.ndarray, theirs: str, check: str) -> None:
        """Our FK of the joints q against the TCP pose (4 x 4) the robot reports: over FK_CHECK_M
        or FK_CHECK_RAD apart, one warning naming the model and the tool. `theirs` names the
        robot's pose, `check` what to compare the tool with."""
        oMfk = self.model.fk(np.asarray(q, dtype=float))
        offset_m = float(np.linalg.norm(oMfk.translation - pose[:3, 3]))
        offset_rad = float(np.linalg.norm(pin.log3(oMfk.rotation.T @ pose[:3, :3])))
        if offset_m > FK_CHECK_M or offset_rad > FK_CHECK_RAD:
            self.log.warning("robot.tool_offset / robot.model: our TCP is %.1f mm and %.1f deg from %s (model %s, "
                             "tool offset %s m, tool quat %s); check them against %s", offset_m * 1e3,
                             np.degrees(offset_rad), theirs, self.model.name, self.model.tool_offset,
                             self.model.tool_quat, check)
        else:
            self.log.info("our TCP is %.2f mm and %.2f deg from %s", offset_m * 1e3, np.degrees(offset_rad), theirs)

    def _reconnect(self, attempt: int) -> int | None:
        """After the back-off for `attempt` earlier failures, a fresh link in place of the lost one.
        Returns the failures so far (0: reconnected), or None when the backend is closing."""
        self._stop.wait(RECONNECT_S[min(attempt, len(RECONNECT_S) - 1)])
        if self._stop.is_set():
            return None
        attempt += 1
        fresh = type(self.link)(self.settings)
        try:
            fresh.start()
        except BackendError as exc:
            self.log.warning("reconnecting to %s (attempt %d): %s", self.settings.host, attempt, exc)
            return attempt
        self.link.stop()
        self.link = fresh
        self.log.info("reconnected to %s", self.settings.host)
        return 0

    def close(self) -> None:
        raise NotImplementedError

    def read_state(self) -> JointState:
        return self.link.read_state()

    def wait_state(self, seq: int, timeout: float) -> JointState:
        try:
            return self.link.wait_state(seq, timeout)
        except BackendError:
            self._stop.wait(timeout)          # reconnecting: the proprioception thread waits, as for a quiet arm
            return self.link.read_state()

    def command_joint_velocity(self, qd) -> None:
        try:
            self.link.command_joint_velocity(qd)
        except BackendError:
            pass

    def hold(self) -> None:
        try:
            self.link.hold()
        except BackendError:
            pass

    def stop(self) -> None:
        self.close()
