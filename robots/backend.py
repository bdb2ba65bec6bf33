"""The one declared base of every robot backend (`RobotBackend`), as ros2_control's SystemInterface is: a
lifecycle, then reading state apart from commanding (as ur_rtde separates them). `LinkBackend` is what
the real arms share: a device client in a child process (robots.child_link), reconnected when lost."""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import pinocchio as pin

from tecdard.host import name_os_thread
from tecdard.options import read_options
from tecdard.robots.backends import BackendError
from tecdard.robots.state_check import StateCheck, StateOptions


# where an arm's own wrench at the TCP comes from (JointState.wrench_source), as `state` and the recordings say
WRENCH_SOURCES = {
    "actual_TCP_force": "UR: the controller's estimate from the joint currents (RTDE actual_TCP_force)",
    "O_F_ext_hat_K": "Franka: the robot's own estimate (O_F_ext_hat_K)",
    "joint_torques": "Franka: J^T F = tau_J - g(q) with franky's model, where the robot estimates none",
    "sim_contact": "the simulator's contact force on the TCP (force only: the torque is not modelled)",
    "ros2_topic": "an observed arm: its driver's geometry_msgs/WrenchStamped on ros2.wrench, in the base frame",
}


@dataclass
class JointState:
    """Proprioception as a robot reports it: joint positions and rates on the daemon's clock."""
    t: float                 # monotonic time of the measurement, s
    q: np.ndarray            # rad
    qd: np.ndarray           # rad/s
    seq: int = 0             # increments with every new measurement
    tcp_twist: np.ndarray | None = None   # [v; w] world-aligned, m/s and rad/s, when the robot reports it
    tcp_force: np.ndarray | None = None   # external force on the TCP, world, N, when the robot estimates it
    tcp_torque: np.ndarray | None = None  # external torque about the TCP, world, N m, when the robot estimates it
    wrench_source: str = ""               # what tcp_force and tcp_torque are: WRENCH_SOURCES' key, "" when neither
    tcp_pose: np.ndarray | None = None    # oMtcp (4 x 4, world) as the robot reports it, from its own calibrated
                                          # kinematics and TCP setting; None: the daemon's FK of q
    grip_force: float | None = None       # the gripper's grasp force, N, where the robot reads one (eta's
                                          # schedule); None: estimator.grip_force_n, the configured constant


@dataclass(frozen=True)
class Recovery:
    """What `recover` did (RobotBackend.recover): the arm can take tasks again (`ok`), the steps taken in order, and
    where it could not, what a person must do (one line)."""
    ok: bool
    steps: tuple[str, ...] = ()
    person: str = ""


@dataclass(frozen=True)
class TopicState:
    """A robot whose state arrives on a front door's topic instead of a link of its own (an arm that ROS 2
    drives): the door subscribes and hands each message over, `take(msg | None, problem | None, source)` (source:
    the publisher's id, None when it did not say)."""
    door: str                      # the front door that subscribes: "ros2" (the ROS 2 node's ros2.joint_states)
    take: Callable
    # messages closer together than this are dropped before they are decoded (keep-last, decimated to the control
    # tick: a 1 kHz publisher then costs about what a 50 Hz one does); 0: every message
    min_period_s: float = 0.0
    take_wrench: Callable | None = None    # the arm's wrench at the TCP, where the door has a topic for it (ros2.wrench)


def joint_rates(qd, nq: int) -> np.ndarray:
    """A joint velocity command as an array, or ValueError naming what is wrong with it."""
    qd = np.asarray(qd, dtype=float)
    if qd.shape != (nq,) or not np.all(np.isfinite(qd)):
        raise ValueError(f"qd: expected {nq} finite joint rates")
    return qd


class RobotBackend:
    """What the daemon asks of a robot. Lifecycle: built from the config (reading only; a bad option is a
    ConfigError from its section), `start` (connect, activate: BackendError naming the robot if it
    cannot), `close` (deactivate, disconnect). Then `read_state`/`wait_state` (the control and
    proprioception threads) and `command_joint_velocity`/`hold` (the control thread).

    What a backend can do it declares, on its class (the daemon reads them before building it) or its
    instance; callers ask these, never the backend's name. The optional behaviours are declared here
    with their defaults: `faults` (the robot's own, held while they last), `annotate` (additions to the
    daemon's events), `imu_source` (the source that reads the fingertip), `checks` (for `tecdard doctor`)."""

    name = "robot"                      # robot.backend
    # -- capabilities ------------------------------------------------------------------
    commands_arm = True                 # False: the daemon only observes the arm (task verbs are refused)
    read_only_reason = ""               # with commands_arm False: the refusal's message
    sends_home = True                   # q_home is where `home` sends the arm (required, inside the workspace);
                                        # False: only the state assumed before the first one is read
    imu_sources: tuple[str, ...] = ("serial",)   # the imu.source values it reads the fingertip through,
                                                 # the first the default
    topic_state: TopicState | None = None        # the state comes from a front door's topic (ROS 2's joint states)
    # How old the newest state may be before it is a fault (`robot_stale`, a protective stop) and the
    # servo holds: `robot.max_state_age_s`, this by default (a backend's own default is its own).
    STATE_AGE_S = 0.05
    state_age_s = STATE_AGE_S
    state_check = None                  # robots.state_check.StateCheck: every state passes it first

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    # -- read ------------------------------------------------------------------------------
    def read_state(self) -> JointState:
        raise NotImplementedError

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s (every new
        measurement, for the estimator, at the robot's own rate)."""
        raise NotImplementedError

    # -- write -----------------------------------------------------------------------------
    def command_joint_velocity(self, qd: np.ndarray) -> None:
        raise NotImplementedError

    def hold(self) -> None:
        """Bring the arm to rest and keep it there."""
        raise NotImplementedError

    # -- recovery ----------------------------------------------------------------------
    recoverable: frozenset = frozenset()    # the fault codes of faults() that `recover` clears on this backend

    def recover(self, timeout_s: float) -> Recovery:
        """Return the arm to a state where tasks can run, within `timeout_s`, or say what a person must do. Runs on
        a thread of its own while the control tick holds the arm (never during a task). This default clears
        nothing: a backend that can, says how."""
        faults = self.faults()
        if not faults:
            return Recovery(True, ("the arm reports no fault: nothing to recover",))
        code, message = next(iter(faults.items()))
        return Recovery(False, (), f"{code}: {message}; `recover` cannot clear it on robot.backend {self.name}")

    def set_resting(self, resting: bool) -> None:
        """The control thread: no task runs (True), or one has started (False). A backend may then
        report fewer states while it rests (robots.child_link.REST_STATE_PERIOD_S)."""

    def feed_states(self, feed) -> bool:
        """Have `feed(js)` called for every state the backend admits, on the backend's own thread
        that receives them; False when it has no such thread (the daemon then reads the states on
        a thread of its own, through wait_state)."""
        return False

    def state_faults(self) -> dict[str, str]:
        """`robot_state` while the state check holds a fault (a state refused, naming its reading)."""
        check = self.state_check
        return {} if check is None or check.fault is None else {"robot_state": check.fault}

    def state_seen_t(self, js: JointState) -> float:
        """When the newest state the robot sent was measured, `js` (the newest one published) or a
        newer one the check refused: a controller that lies is robot_state's fault, not a silent one's."""
        check = self.state_check
        return js.t if check is None or check.fault is None else max(js.t, check.seen_t)

    def _check_states(self, ctx, source: str) -> None:
        """The state check and the age budget, from the `robot` section (`source` names who reports
        the states in the fault's message)."""
        opts = read_options(StateOptions, ctx.cfg.section("robot"), {"max_state_age_s": self.STATE_AGE_S})
        self.state_check = StateCheck(ctx.model, source, opts.joint_limit_margin_rad)
        self.state_age_s = opts.max_state_age_s

    # -- optional, with defaults ---------------------------------------------------------
    @property
    def world_control(self):
        """A simulated world's hooks for a task (`home --reset-world`: sim.backend.WorldControl); None for
        a real arm's world."""
        return None

    def faults(self) -> dict[str, str]:
        """The robot's own faults that hold now, code -> message (raised and cleared as the daemon's)."""
        return {}

    def annotate(self, event: dict) -> dict:
        """An event with what this backend adds to it (the simulator's truth on a task's end)."""
        return event

    def imu_source(self, kind: str, section):
        """The fingertip's IMU source for `imu.source: kind`, one of imu_sources (`section`: the config's
        `imu`). A real arm has the board on serial; the simulator's backend also has its own."""
        from tecdard.drivers.serial_imu import SerialImuSource, SerialParams
        return SerialImuSource(SerialParams.from_config(section.section("serial")))

    def checks(self) -> list:
        """Whether this host can reach the robot (tecdard.host.Check each), for `tecdard doctor`."""
        return []


RECONNECT_S = (0.5, 1.0, 2.0, 4.0)      # back-off between reconnect attempts, then the last one repeated
FK_CHECK_M = 0.003         # our FK and the robot's own TCP pose further apart than this: said at start
FK_CHECK_RAD = 0.0175      # ... or turned by more than this (1 degree)


def rig_section(ctx, backend: str, models: tuple[str, ...], arm: str, host_is: str):
    """The `robot.<backend>` section of a real arm's backend, after the checks every such backend
    makes: robot.model is one of `models` and the section names a host (a ConfigError from the
    section naming the key otherwise)."""
    robot = ctx.cfg.section("robot")
    if ctx.model.name not in models:
        raise robot.error("model", f"{ctx.model.name!r} is no {arm} arm; with robot.backend {backend} use one of "
                                   f"{', '.join(models)}")
    section = robot.section(backend)
    if not section.has("host"):
        raise section.error("host", f"required with robot.backend {backend} ({host_is})")
    return section


class LinkBackend(RobotBackend):
    """A backend that reaches its robot through a ChildLink (`self.link`, replaced when it reconnects;
    `self._stop` set on close). A link that is down answers with its last state and takes no
    command: its fault has stopped the task already. The fingertip board is read over serial."""

    link: Any                          # robots.child_link.ChildLink (its subclass: the arm's)
    settings: object
    model: object                      # robots.model.ArmModel
    log: object                        # the backend's logger
    _stop: threading.Event

    def _attach(self, ctx, link, source: str) -> None:
        """What every link backend holds once its settings are read: the arm model, the state
        check (`source`: who reports the states) and the link (not yet started)."""
        self.nq = ctx.model.nq
        self.model = ctx.model
        self._check_states(ctx, source)
        self.link = link
        link.gate = self.state_check
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._resting = False
        self._feed = None                  # feed_states: every admitted state, on the link's reader

    def _supervise_in_background(self, name: str) -> None:
        def run():
            name_os_thread(name)
            self._supervise()
        self._supervisor = threading.Thread(target=run, name=name, daemon=True)
        self._supervisor.start()

    def _supervise(self) -> None:
        raise NotImplementedError

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
        self.state_check.reset()              # a new link: no previous state to measure a jump from
        fresh.gate = self.state_check
        fresh.on_state = self._feed
        try:
            fresh.start()
        except BackendError as exc:
            self.log.warning("reconnecting to %s (attempt %d): %s", self.settings.host, attempt, exc)
            return attempt
        fresh.set_resting(self._resting)      # a fresh child sends every state until told
        self.link.stop()
        self.link = fresh
        self.log.info("reconnected to %s", self.settings.host)
        return 0

    def state_seen_t(self, js: JointState) -> float:
        """As any backend's, but while the link is down its own fault (robot_link) says why no
        state comes: never judged stale meanwhile (the servo holds all the same)."""
        link = self.link
        if link.exited.is_set() or link.fault:
            return math.inf
        return super().state_seen_t(js)

    def close(self) -> None:
        self._stop.set()
        self.link.stop()
        if self._supervisor is not None:
            self._supervisor.join(2.0)

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

    def set_resting(self, resting: bool) -> None:
        self._resting = resting
        self.link.set_resting(resting)

    def feed_states(self, feed) -> bool:
        self._feed = self.link.on_state = feed
        return True
