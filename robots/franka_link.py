"""franky in a process of its own: the daemon's link to a Franka arm (FR3 or Panda) over the FCI.

Why a process of its own:
- `franky.Robot()` has no timeout. A server that accepts the connection and never answers, or
  an older libfranka against a newer server, leaves it waiting for ever (issue 22's own
  measurements), and a pybind11 call that waits may hold the GIL: every thread of the caller would
  wait with it. In a child, the parent's deadline ends the child instead.
- libfranka's control loop runs in a thread of franky's own at 1 kHz. In the child it competes
  with the child only, not with the daemon's estimator.

The child connects (franky.Robot, and franky.Gripper when the arm has a hand), then sends every
new robot state to the parent and carries out the daemon's commands:
- `qd`: a JointVelocityMotion to these joint rates, re-issued every control tick. Its duration is
  the watchdog: franky holds the target that long after reaching it, then stops, so a daemon that
  stops commanding stops the arm one watchdog later.
- `hold`: franky's JointVelocityStopMotion (the arm decelerates at its dynamics limits and rests).
- `recover`: franky's automatic error recovery (recover_from_errors), after a reflex.
- `close`: stop the motion and end.

Every state carries the external force at the TCP: the robot's own estimate (O_F_ext_hat_K)
where it gives one; otherwise from the joint torques, Jᵀ F = τ_J − g(q), with franky's own model
(libfranka's, the robot's dynamics and its configured load). franky-sim reports no force
estimate.
"""
from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import wait

import numpy as np

from tecdard.drivers.timesync import SlewClock
from tecdard.options import option
from tecdard.robots.backend import JointState, joint_rates
from tecdard.robots.backends import BackendError
from tecdard.robots.child_link import ChildLink
from tecdard.robots.franka_server import (CONNECT_INCOMPATIBLE, LIBFRANKA_ROBOT_SERVER_VERSION, ROBOT_PORT,
                                          server_version)

log = logging.getLogger("tecdar.franka")

NQ = 7
LINK_SILENT_S = 0.5                     # no new robot state for this long: the link is lost
GRIP_HZ = 10.0                          # the hand's state is read this often
ROBOT_PERIOD_S = 0.001                  # the robot's state rate, 1 kHz
STATE_POLL_S = 0.0005                   # between state reads while a motion runs (franky then answers at once)
GRAVITY = np.array([0.0, 0.0, -9.81])
FORCE_DAMPING = 1e-6                    # m^2-scale damping of J Jᵀ in the force's least squares
FORCE_FROM_TORQUES = "torques"          # FrankaState.force_source: Jᵀ F = τ_J − g(q)
FORCE_FROM_ROBOT = "robot"              # the robot's own O_F_ext_hat_K
ERROR_MODES = ("Reflex", "UserStopped", "Other")   # robot modes that hold a fault
STATE_FLOATS = 40                       # a state on the pipe: t, rx_t, q, dq, O_T_EE, f_ext (6), grip width, grasped


class FrankaLinkError(BackendError):
    """The robot could not be reached, refused the link, or the link has gone."""


@dataclass(frozen=True)
class FrankaLinkSettings:
    """The `robot.franka` section (docs/franka.md): the robot's FCI and how it is driven."""
    host: str = option("", "the robot's FCI address", required=True, max_len=253)
    realtime: str = option("enforce", "franky's RealtimeConfig: enforce (a real arm), ignore (simulation)",
                           choices=("enforce", "ignore"))
    connect_timeout_s: float = option(10.0, "a robot that does not answer within this is an error", unit="s",
                                      above=0.0, maxval=120.0)
    watchdog_s: float = option(0.06, "a velocity motion's hold after its target: the arm stops this long after the "
                                     "daemon's last command (default 3 control ticks, at least 2)", unit="s",
                               minval=0.004, maxval=0.5)
    relative_dynamics_factor: float = option(0.5, "franky's scaling of the arm's velocity, acceleration and jerk "
                                                  "limits", minval=0.05, maxval=1.0)
    gripper: bool = option(True, "read the hand's state (franky.Gripper)")
    grasp_force_n: float = option(20.0, "the grasp's commanded force: the grip force while the hand holds",
                                  unit="N", above=0.0, maxval=140.0)
    state_rate_hz: float = option(500.0, "robot states handed to the daemon per second (the robot's are 1 kHz)",
                                  unit="Hz", minval=100.0, maxval=1000.0)


@dataclass(frozen=True)
class FrankaState:
    """One robot state as the child read it."""
    robot_t: float               # the robot's clock, s
    rx_t: float                  # the child's monotonic clock when read, s
    q: tuple
    dq: tuple
    O_T_EE: tuple                # 16, column-major: the robot's own TCP pose (franky's, from the commanded joints in franky-sim)
    f_ext: tuple                 # external wrench at the TCP, base frame: force N, torque N m
    force_source: str            # FORCE_FROM_ROBOT or FORCE_FROM_TORQUES
    mode: str                    # franky's RobotMode name: Idle, Move, Reflex, UserStopped, ...
    errors: str                  # the robot's current errors, "" when none
    grip_width: float | None     # m, the hand's opening (None: no hand read)
    grasped: bool | None


def _matrix(affine) -> np.ndarray:
    m = affine.matrix
    return np.asarray(m() if callable(m) else m, dtype=float)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"


def version_mismatch(host: str, theirs) -> str:
    return (f"robot.franka.host: the robot at {host} runs robot server version {theirs}; this franky (libfranka "
            f"0.21.2) speaks version {LIBFRANKA_ROBOT_SERVER_VERSION}. Install the franky-control release built for "
            f"the robot's system version, or update the robot")


def connect_problem(host: str, exc: BaseException) -> str:
    """franky's connect exception as one line a Franka user can act on."""
    name = type(exc).__name__
    text = str(exc)
    if name == "IncompatibleVersionException":
        found = re.search(r"server version:?\s*(\d+).*?library version:?\s*(\d+)", text, re.S | re.I)
        return version_mismatch(host, found.group(1) if found else "?")
    if name == "RealtimeException":
        return (f"robot.franka.realtime: enforce, but this kernel has no realtime capability ({_first_line(exc)}); "
                f"run on a PREEMPT_RT kernel with realtime limits for this user (`tecdard doctor` says what is "
                f"missing), or set realtime: ignore in simulation only")
    if name == "NetworkException":
        return f"robot.franka.host: no Franka robot answered at {host} ({_first_line(exc)})"
    return f"robot.franka.host: {host} refused the link: {_first_line(exc)}"


class _Force:
    """The external force at the TCP from the joint torques when the robot estimates none:
    Jᵀ F = τ_J − g(q), solved in least squares with franky's model of the arm."""

    def __init__(self, model, frame):
        self.model, self.frame = model, frame

    def __call__(self, state) -> tuple[np.ndarray, str]:
        f_robot = np.asarray(state.O_F_ext_hat_K, dtype=float)
        if np.any(f_robot != 0.0):
            return f_robot[:6], FORCE_FROM_ROBOT
        tau_ext = np.asarray(state.tau_J, dtype=float) - np.asarray(self.model.gravity(state, GRAVITY), dtype=float)
        J = np.asarray(self.model.zero_jacobian(self.frame, state), dtype=float)
        # least squares through the normal equations, damped so a singular pose stays finite
        # (a tenth of lstsq's cost, at 1 kHz)
        wrench = np.linalg.solve(J @ J.T + FORCE_DAMPING * np.eye(6), J @ tau_ext)
        return wrench, FORCE_FROM_TORQUES


def _motion(franky, settings: FrankaLinkSettings, qd) -> object:
    return franky.JointVelocityMotion(np.asarray(qd, dtype=float),
                                      duration=franky.Duration(max(int(settings.watchdog_s * 1e3), 1)))


def child_main(settings: FrankaLinkSettings, cmd_rx, state_tx) -> None:
    """The child: connect, then stream states and carry out commands until told to close or the link goes."""
    try:
        import franky
    except ImportError as exc:
        state_tx.send(("error", f"robot.backend franka needs franky (pip install 'tecdar[franka]'): {exc}"))
        return
    realtime = franky.RealtimeConfig.Enforce if settings.realtime == "enforce" else franky.RealtimeConfig.Ignore
    try:
        robot = franky.Robot(settings.host, realtime_config=realtime,
                             relative_dynamics_factor=settings.relative_dynamics_factor)
        first = robot.state
    except Exception as exc:
        state_tx.send(("error", connect_problem(settings.host, exc)))
        return
    _FrankaChild(franky, robot, settings, state_tx).run(first, cmd_rx)


class _FrankaChild:
    """The child's loop on a connected robot: its commands, its states at the daemon's rate, its faults."""

    def __init__(self, franky, robot, settings: FrankaLinkSettings, state_tx):
        self.franky, self.robot, self.settings, self.state_tx = franky, robot, settings, state_tx
        self.gripper = self._gripper()
        self.grip = {"width": None, "grasped": None}
        self.closing = threading.Event()
        self.force = _Force(robot.model, franky.Frame.EndEffector)
        self.holding = True                  # a stop motion needs sending once, not every tick
        self.fault = ""
        self.lost = False
        self.sent_mode = None
        self.packed = np.empty(STATE_FLOATS)
        self.sent_t = -np.inf
        self.last_t = None
        self.last_new = time.monotonic()
        self.state_period = 1.0 / settings.state_rate_hz
        self.period = self.state_period      # between the states sent: longer while the daemon rests

    def _gripper(self):
        if not self.settings.gripper:
            return None
        try:
            return self.franky.Gripper(self.settings.host)
        except Exception as exc:           # an arm without a hand, or its server down: said, not fatal
            self.state_tx.send(("note", f"no gripper state from {self.settings.host}: {_first_line(exc)}"))
            return None

    def _read_gripper(self) -> None:
        """The hand's state at GRIP_HZ on a thread of its own: its reads wait for its own server
        (2 s on a timeout), and the arm's states must not wait with them."""
        while not self.closing.wait(1.0 / GRIP_HZ):
            try:
                gs = self.gripper.state
                self.grip["width"], self.grip["grasped"] = float(gs.width), bool(gs.is_grasped)
            except Exception:
                self.grip["width"] = self.grip["grasped"] = None

    def run(self, first, cmd_rx) -> None:
        if self.gripper is not None:
            threading.Thread(target=self._read_gripper, name="franka-gripper", daemon=True).start()
        ee = _matrix(first.O_T_EE)
        gripper_version = int(self.gripper.server_version) if self.gripper is not None else None
        self.state_tx.send(("ready", {"O_T_EE": tuple(ee.ravel(order="F")), "q": tuple(first.q),
                                      "gripper_version": gripper_version}))
        try:
            while True:
                while cmd_rx.poll():
                    if not self._command(cmd_rx.recv()):
                        return
                # a motion's own exception (a reflex) surfaces here, once
                self._call("motion", self.robot.poll_motion)
                wait_s = self._state()
                if wait_s is None:
                    return
                wait([cmd_rx], wait_s)
        except (EOFError, OSError, BrokenPipeError):
            return                      # the daemon has gone
        except Exception as exc:        # franky's NetworkException: the robot has gone
            self.lost = True
            try:
                self.state_tx.send(("lost", _first_line(exc)))
            except (OSError, BrokenPipeError):
                pass
        finally:
            self.closing.set()
            if not self.lost:
                try:
                    self.robot.stop()
                except Exception:
                    pass

    def _report_fault(self, text: str) -> None:
        if text != self.fault:
            self.fault = text
            self.state_tx.send(("fault", text) if text else ("clear",))

    def _call(self, what: str, fn) -> None:
        """A franky call that may raise a motion's exception (a reflex, a preemption, a rejected
        motion): the fault holds until a command is taken again or the recovery clears it."""
        try:
            fn()
        except Exception as exc:
            name = type(exc).__name__
            if name == "NetworkException":
                raise
            if name == "ControlException" and "preempted" in str(exc).lower():
                return                     # a motion replaced by the next command, or stopped: no fault
            self._report_fault(f"{what}: {_first_line(exc)}")
        else:
            if self.fault and what != "motion" and not self.fault.startswith("robot mode"):
                self._report_fault("")

    def _command(self, msg: tuple) -> bool:
        """One command from the daemon; False when it says close."""
        franky, robot = self.franky, self.robot
        if msg[0] == "qd":
            self.holding = False
            motion = _motion(franky, self.settings, msg[1])
            self._call("velocity command", lambda: robot.move(motion, asynchronous=True))
        elif msg[0] == "hold":
            if not self.holding:
                self.holding = True
                self._call("hold", lambda: robot.move(franky.JointVelocityStopMotion(), asynchronous=True))
        elif msg[0] == "recover":
            self._recover()
        elif msg[0] == "grip":
            threading.Thread(target=self._grip, args=(msg[1],), name="franka-grip", daemon=True).start()
        elif msg[0] == "grip_stop" and self.gripper is not None:
            self._call("gripper stop", self.gripper.stop)
        elif msg[0] == "rest":                 # child_link.REST_STATE_PERIOD_S while the daemon rests, else 0
            self.period = max(self.state_period, float(msg[1]))
        elif msg[0] == "close":
            return False
        return True

    def _grip(self, spec: tuple) -> None:
        """A grasp or a move of the hand (franky's calls block until the fingers stop), on a thread of its
        own: the arm's states and commands go on meanwhile. Answers ("gripped", ok, why)."""
        if self.gripper is None:
            self.state_tx.send(("gripped", False, "no Franka Hand answered at connect"))
            return
        try:
            # ("grasp", width, speed, force, epsilon_inner, epsilon_outer) or ("move", width, speed)
            ok = bool(self.gripper.grasp(*spec[1:]) if spec[0] == "grasp" else self.gripper.move(*spec[1:]))
        except Exception as exc:
            self.state_tx.send(("gripped", False, _first_line(exc)))
        else:
            self.state_tx.send(("gripped", ok, ""))

    def _recover(self) -> None:
        ok = False
        try:
            ok = bool(self.robot.recover_from_errors())
        except Exception as exc:
            if type(exc).__name__ == "NetworkException":
                raise
            self.state_tx.send(("recovered", False, _first_line(exc)))
        else:
            if ok and not self.fault.startswith("robot mode"):
                self._report_fault("")
            self.state_tx.send(("recovered", ok, "" if ok else "the robot refused its error recovery"))

    def _state(self) -> float | None:
        """Read the robot's state and hand every one the daemon takes to it; how long to wait for a
        command before the next read, or None when the robot has gone silent (`lost` sent)."""
        st = self.robot.state                # blocks for the next packet (1 ms) when no motion runs
        now = time.monotonic()
        t = float(st.time.to_sec())
        if t == self.last_t:
            if now - self.last_new > LINK_SILENT_S:
                self.lost = True
                self.state_tx.send(("lost", f"no state from the robot for {now - self.last_new:.1f} s"))
                return None
            return STATE_POLL_S
        self.last_t, self.last_new = t, now
        if t - self.sent_t < self.period - 2.5e-4:
            return 0.0       # between the states the daemon takes (faults and force are read at its rate)
        self.sent_t = t
        self._send_state(st, t, now)
        # nothing to read until a robot period before the next state the daemon takes: wait for a
        # command meanwhile (it is carried out at once) rather than poll franky every STATE_POLL_S
        # (waiting up to the next state itself would miss it)
        return max(self.period - ROBOT_PERIOD_S - (time.monotonic() - now), 0.0)

    def _send_state(self, st, t: float, now: float) -> None:
        errors = repr(st.current_errors).strip()
        errors = "" if errors in ("[]", "") else errors
        mode = st.robot_mode.name
        if errors or mode in ERROR_MODES:
            self._report_fault(f"robot mode {mode}" + (f", errors {errors}" if errors else ""))
        elif self.fault.startswith("robot mode"):
            self._report_fault("")
        f_ext, source = self.force(st)
        if (mode, errors, source) != self.sent_mode:
            self.sent_mode = (mode, errors, source)
            self.state_tx.send(("mode", mode, errors, source))
        # one float array per state: a dataclass took 43 us to pickle, a tenth of the loop at 1 kHz
        packed = self.packed
        packed[0], packed[1] = t, now
        packed[2:9], packed[9:16] = st.q, st.dq
        packed[16:32] = _matrix(st.O_T_EE).ravel(order="F")
        packed[32:38] = f_ext
        packed[38] = np.nan if self.grip["width"] is None else self.grip["width"]
        packed[39] = np.nan if self.grip["grasped"] is None else float(self.grip["grasped"])
        self.state_tx.send(("state", packed))


class FrankaLink(ChildLink):
    """The daemon's handle on the child: receive (read_state, wait_state) and control
    (command_joint_velocity, hold), as any robot backend; `fault` says why the link is unusable
    and `robot_fault` what the robot reports (a reflex, a user stop)."""

    error = FrankaLinkError
    process_name = "tecdar-franka"
    reader_name = "franka-link"
    child = staticmethod(child_main)

    def __init__(self, settings: FrankaLinkSettings):
        super().__init__(settings, settings.connect_timeout_s)
        self.franka_state: FrankaState | None = None
        self._mode = ("", "", "")                   # the robot's mode, errors and force source, as last sent
        self._seq = 0
        self._sync = SlewClock()
        self._last_t = -np.inf
        self.robot_fault: str = ""                  # the robot's reflex or stop, "" when none
        self.recovery: threading.Event = threading.Event()   # set when a recovery answer arrives
        self.recovery_result: tuple[bool, str] = (False, "")
        self.gripped: threading.Event = threading.Event()     # set when the hand's grasp or move answers
        self.grip_result: tuple[bool, str] = (False, "")
        self.identity: dict = {}                    # what the child read at connect (O_T_EE, q, gripper version)
        self.server_version: int | None = None      # the robot server's, from its Connect reply

    def start(self) -> None:
        """Check the robot server's version, then connect, all within settings.connect_timeout_s,
        or FrankaLinkError naming the host and what failed."""
        self._check_version()
        super().start()

    def _no_answer(self, timeout_s: float) -> str:
        return (f"robot.franka.host: no answer from a Franka robot at {self.settings.host} within {timeout_s:g} s "
                f"(franky.Robot still waiting: nothing that speaks the FCI there, or a robot server this libfranka "
                f"does not match)")

    def _ended(self, exitcode) -> str:
        return f"robot.franka.host: the link to {self.settings.host} ended at start (exit code {exitcode})"

    def _refused(self, reason: str) -> str:
        return reason                               # the child's line (connect_problem) names host and cause

    def _no_state(self) -> str:
        return f"no state from {self.settings.host} yet"

    def _not_running(self) -> str:
        return f"the link to {self.settings.host} is not running"

    def _ready(self, payload: tuple) -> None:
        self.identity = payload[0]

    def _check_version(self) -> None:
        host, timeout = self.settings.host, self.settings.connect_timeout_s
        try:
            status, version = server_version(host, timeout)
        except ConnectionRefusedError:
            raise FrankaLinkError(f"robot.franka.host: no Franka robot answered at {host} (connection to port "
                                  f"{ROBOT_PORT} refused: FCI not enabled in Desk, or another address)") from None
        except OSError as exc:
            raise FrankaLinkError(f"robot.franka.host: no answer from a Franka robot at {host} within {timeout:g} s "
                                  f"({exc.strerror or type(exc).__name__})") from None
        except ValueError as exc:
            raise FrankaLinkError(f"robot.franka.host: {exc}") from None
        self.server_version = version
        if status == CONNECT_INCOMPATIBLE or version != LIBFRANKA_ROBOT_SERVER_VERSION:
            raise FrankaLinkError(version_mismatch(host, version))

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "state":
            a = msg[1]
            st = FrankaState(float(a[0]), float(a[1]), tuple(a[2:9]), tuple(a[9:16]), tuple(a[16:32]),
                             tuple(a[32:38]), self._mode[2], self._mode[0], self._mode[1],
                             None if a[38] != a[38] else float(a[38]), None if a[39] != a[39] else bool(a[39]))
            self._sync.add(st.robot_t, st.rx_t)
            self._seq += 1
            self.franka_state = st
            self._publish(self._joint_state(st))
        elif kind == "mode":
            self._mode = msg[1:]
        elif kind == "fault":
            self.robot_fault = msg[1]
        elif kind == "clear":
            self.robot_fault = ""
        elif kind == "recovered":
            self.recovery_result = (bool(msg[1]), msg[2])
            self.recovery.set()
        elif kind == "gripped":
            self.grip_result = (bool(msg[1]), msg[2])
            self.gripped.set()
        elif kind == "note":
            self.notes.append(msg[1])

    def _gone(self) -> None:
        if self.fault is None:
            self.fault = f"the link to {self.settings.host} has gone"

    def _joint_state(self, st: FrankaState) -> JointState:
        """A robot state as the daemon's: its clock, the measured joints (the daemon's FK gives the
        TCP), the external force, and the grasp's force while the hand holds (None otherwise: the
        estimator's configured grip force)."""
        # the robot's clock on the host's (drivers.timesync.SlewClock: smooth, and never back)
        t = float(self._sync.to_host(st.robot_t))
        if t <= self._last_t:               # a robot clock that stepped back (a restart): its own time order
            t = self._last_t + 1e-4
        self._last_t = t
        return JointState(t=t, q=np.array(st.q), qd=np.array(st.dq),
                          seq=self._seq, tcp_force=np.array(st.f_ext[:3]), tcp_torque=np.array(st.f_ext[3:6]),
                          wrench_source="O_F_ext_hat_K" if st.force_source == FORCE_FROM_ROBOT else "joint_torques",
                          grip_force=self.settings.grasp_force_n if st.grasped else None)

    # -- RobotControl ---------------------------------------------------------
    def command_joint_velocity(self, qd: np.ndarray) -> None:
        self._send(("qd", tuple(float(x) for x in joint_rates(qd, NQ))))

    def hold(self) -> None:
        """Bring the arm to rest with franky's stop motion, sent once per hold."""
        self._send(("hold",))

    def grip(self, spec: tuple, timeout_s: float) -> tuple[bool, str]:
        """The hand's ("grasp", width, speed, force, epsilon_inner, epsilon_outer) or ("move", width, speed):
        (grasped or reached, why it failed: "" when it answered)."""
        self.gripped.clear()
        self._send(("grip", tuple(spec)))
        if not self.gripped.wait(timeout_s):
            self.grip_stop()
            return False, f"no answer from the hand within {timeout_s:g} s (stopped)"
        return self.grip_result

    def grip_stop(self) -> None:
        self._send(("grip_stop",))

    def recover(self, timeout_s: float = 5.0) -> tuple[bool, str]:
        """franky's automatic error recovery: (succeeded, why not)."""
        self.recovery.clear()
        self._send(("recover",))
        if not self.recovery.wait(timeout_s):
            return False, f"no answer to the error recovery within {timeout_s:g} s"
        return self.recovery_result
