"""The ur-rtde clients in a process of their own: the daemon's link to a Universal Robots controller.

Why a process of their own (both seen against tests/fakes/fake_ur.py):
- ur-rtde's pybind11 binding holds the GIL while it blocks. A connect waits for the controller's
  handshake, and every Python thread of the caller waits with it: the control loop, the IMU path.
- When the controller drops the connection, ur-rtde's background threads can end with an uncaught
  exception, and `terminate` aborts the whole process.
In a child both cost the child only. The daemon sees a link that reports `lost` and can reconnect.

The child connects (RTDEReceiveInterface, then RTDEControlInterface, which uploads its control
script), then streams every new controller state to the parent and carries out speedJ and stop
commands. The parent maps the controller's timestamps onto its monotonic clock (drivers.timesync.
SlewClock: the lower envelope of arrival minus controller time, which moves at most 2 ms a second,
so a run of late states shows as late rather than moving the clock) and hands out JointStates as
any backend, once they pass its state check (robots.state_check).

Frames: the controller reports its TCP pose, speed and force in its own base frame, which is a UR
model's world (robots.model.UR_ARMS), so they pass as they are; the pose's rotation vector becomes
a matrix.
"""
from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass
from multiprocessing.connection import wait

import numpy as np

import pinocchio as pin

from tecdard.drivers.timesync import SlewClock
from tecdard.options import option
from tecdard.robots.backend import JointState, joint_rates
from tecdard.robots.backends import BackendError
from tecdard.robots.child_link import ChildLink

log = logging.getLogger("tecdar.ur")

DASHBOARD_TIMEOUT_MS = 2000
CONTROLLER_CYCLE_S = 0.002     # an e-Series controller's cycle (500 Hz), the fastest RTDE rate
SCRIPT_START_S = 1.0          # a re-uploaded control script runs within this
REFUSED_AFTER_S = 0.05         # commands refused this long, with no stop to explain it: the link's fault
STOP_DECEL_RAD_S2 = 2.0        # speedStop's deceleration when the daemon holds or stops the arm
LINK_SILENT_S = 0.5            # no new controller state for this long: the link is lost (ur-rtde's own
                               # isConnected stays true while its control interface tries to reconnect)
UR_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force",
                "robot_mode", "safety_mode", "safety_status_bits", "robot_status_bits", "runtime_state"]
PROTECTIVE_STOPPED_BIT = 2     # safety_status_bits
EMERGENCY_STOPPED_BITS = (5, 6, 7)     # system, robot, any emergency stop
PROGRAM_RUNNING_BIT = 1        # robot_status_bits
ROBOT_MODE_RUNNING = 7
NQ = 6


class UrLinkError(BackendError):
    """The controller could not be reached, refused the link, or the link has gone."""


@dataclass(frozen=True)
class UrLinkSettings:
    """The `robot.ur` section (docs/ur.md): the controller and how it is driven."""
    host: str = option("", "the controller's address", required=True, max_len=253)
    frequency_hz: float = option(-1.0, "RTDE's rate; -1: the controller's own (500 Hz e-Series, 125 Hz CB3)",
                                 unit="Hz", minval=-1.0, maxval=500.0)
    accel_rad_s2: float = option(4.0, "speedJ's acceleration bound", unit="rad/s^2", above=0.0, maxval=40.0)
    command_time_s: float = 0.02          # speedJ's time: the control tick (the controller stops after it)
    connect_timeout_s: float = option(10.0, "a controller that does not answer within this is an error", unit="s",
                                      above=0.0, maxval=120.0)
    watchdog_hz: float = option(10.0, "the controller stops the program when the daemon writes less often (at most "
                                      "half the control tick's rate)", unit="Hz", minval=2.0, maxval=500.0)
    allow_power_on: bool = option(False, "`recover` may power the arm on and release its brakes through the dashboard "
                                         "(else it says a person must, on the pendant)")


@dataclass(frozen=True)
class UrState:
    """One controller state as the child read it."""
    controller_t: float          # the controller's clock, s
    rx_t: float                  # the child's monotonic clock when read, s
    q: tuple
    qd: tuple
    tcp_pose: tuple              # x, y, z (m) and a rotation vector (rad), base frame, with the controller's TCP
    tcp_speed: tuple             # v (m/s) and w (rad/s), base frame
    tcp_force: tuple             # force (N) and torque (N m) at the TCP, base frame
    robot_mode: int
    safety_mode: int
    safety_bits: int
    program_running: bool

    @property
    def protective_stopped(self) -> bool:
        return bool(self.safety_bits >> PROTECTIVE_STOPPED_BIT & 1)

    @property
    def emergency_stopped(self) -> bool:
        return any(self.safety_bits >> b & 1 for b in EMERGENCY_STOPPED_BITS)


def controller_identity(host: str) -> dict:
    """The arm type and software version the controller's dashboard server reports, and on an
    e-Series whether it is in remote control ({"model": "UR5", "version": "5.11.0.0",
    "remote_control": True}), or {} when the dashboard does not answer."""
    import dashboard_client
    db = dashboard_client.DashboardClient(host)
    try:
        db.connect(DASHBOARD_TIMEOUT_MS)
        found = re.search(r"(\d+\.\d+\.\d+(\.\d+)?)", db.polyscopeVersion())
        identity = {"model": db.getRobotModel().strip(), "version": found.group(1) if found else ""}
        if identity["version"] and int(identity["version"].split(".")[0]) >= 5:
            identity["remote_control"] = bool(db.isInRemoteControl())      # e-Series only
        return identity
    except Exception:
        return {}
    finally:
        try:
            db.disconnect()
        except Exception:
            pass


def restart_script(ctl, settings: UrLinkSettings) -> None:
    """Upload ur-rtde's control script again, after a stop has cleared. The controller keeps its RTDE
    input registers across programs, and the new script runs the command they hold: the last
    speedJ written before the stop. So zeros go in as soon as it runs (then the arm ramps from
    rest at most a few controller cycles towards that old speed, at the speedJ acceleration), and
    a watchdog, which a new program starts without."""
    ctl.reuploadScript()
    deadline = time.monotonic() + SCRIPT_START_S
    while not ctl.isProgramRunning() and time.monotonic() < deadline:
        time.sleep(CONTROLLER_CYCLE_S)      # ur-rtde offers no wait for it: its state, once a cycle
    ctl.speedJ([0.0] * NQ, settings.accel_rad_s2, settings.command_time_s)
    ctl.setWatchdog(settings.watchdog_hz)


def child_main(settings: UrLinkSettings, cmd_rx, state_tx) -> None:
    """The child: connect, then stream states and carry out commands until told to close or the link goes."""
    import rtde_control
    import rtde_receive
    identity = controller_identity(settings.host)
    try:
        rx = rtde_receive.RTDEReceiveInterface(settings.host, settings.frequency_hz, UR_VARIABLES)
        ctl = rtde_control.RTDEControlInterface(settings.host, settings.frequency_hz)
        # The controller's RTDE watchdog: the daemon's control tick writes the command register every
        # tick (speedJ, or speedJ of zeros when it holds); if the daemon stalls for 1 / watchdog_hz s,
        # the controller stops the program and the arm, whatever speed it was told last.
        if not ctl.setWatchdog(settings.watchdog_hz):
            raise RuntimeError(f"the controller refused the RTDE watchdog at {settings.watchdog_hz:g} Hz")
    except Exception as exc:
        state_tx.send(("error", f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"))
        return
    state_tx.send(("ready", identity))
    last_t = None
    last_new = time.monotonic()
    lost = False
    refusing = False
    refused_since = None
    rest_period_s, sent_t = 0.0, -math.inf    # while the daemon rests, one state per rest_period_s (its clock)

    def outcome(ok: bool, what: str) -> None:
        """A refusal is the link's fault only when the controller's state does not explain it (a
        protective stop, or the program stopped, has its own fault), and only once it has lasted
        REFUSED_AFTER_S: the receive stream may show the stop a cycle after the command failed."""
        nonlocal refusing, refused_since
        if ok:
            refused_since = None
            if refusing:
                refusing = False
                state_tx.send(("accepted", what))
            return
        if rx.isProtectiveStopped() or rx.isEmergencyStopped() or not rx.getRobotStatus() >> PROGRAM_RUNNING_BIT & 1:
            refused_since = None
            return
        now = time.monotonic()
        refused_since = now if refused_since is None else refused_since
        if not refusing and now - refused_since >= REFUSED_AFTER_S:
            refusing = True
            state_tx.send(("refused", what))
    try:
        while True:
            while cmd_rx.poll():
                msg = cmd_rx.recv()
                if msg[0] == "speedj":
                    outcome(ctl.speedJ(list(msg[1]), settings.accel_rad_s2, settings.command_time_s), "speedJ")
                elif msg[0] == "stop":
                    outcome(ctl.speedStop(STOP_DECEL_RAD_S2), "speedStop")
                elif msg[0] == "reupload":
                    restart_script(ctl, settings)
                elif msg[0] == "rest":
                    rest_period_s = float(msg[1])
                elif msg[0] == "close":
                    return
            if not rx.isConnected():
                lost = True
                state_tx.send(("lost", "the controller closed the RTDE connection"))
                return
            t = rx.getTimestamp()
            now = time.monotonic()
            if t == last_t and now - last_new > LINK_SILENT_S:
                lost = True
                state_tx.send(("lost", f"no state from the controller for {now - last_new:.1f} s"))
                return
            if t != last_t:
                last_t, last_new = t, now
            # every new state, or while the daemon rests one per rest_period_s (a clock that went back
            # starts afresh)
            if t != sent_t and not 0.0 <= t - sent_t < rest_period_s - CONTROLLER_CYCLE_S / 2:
                sent_t = t
                state_tx.send(("state", UrState(
                    t, time.monotonic(), tuple(rx.getActualQ()), tuple(rx.getActualQd()), tuple(rx.getActualTCPPose()),
                    tuple(rx.getActualTCPSpeed()), tuple(rx.getActualTCPForce()), rx.getRobotMode(),
                    rx.getSafetyMode(), rx.getSafetyStatusBits(), bool(rx.getRobotStatus() >> PROGRAM_RUNNING_BIT & 1))))
            # a command wakes the loop at once; otherwise the controller's state is polled at twice
            # its fastest rate (ur-rtde's receive interface offers no wait for a new state)
            wait([cmd_rx], CONTROLLER_CYCLE_S / 2)
    except (EOFError, OSError, BrokenPipeError):
        return                      # the daemon has gone
    finally:
        # on a lost link the client's calls block in its reconnect: the parent ends this process
        for step in () if lost else (lambda: ctl.speedStop(STOP_DECEL_RAD_S2), ctl.stopScript, ctl.disconnect,
                                     rx.disconnect):
            try:
                step()
            except Exception:
                pass


class UrLink(ChildLink):
    """The daemon's handle on the child: receive (read_state, wait_state) and control
    (command_joint_velocity, hold), as any robot backend; `fault` says why the link is unusable."""

    error = UrLinkError
    process_name = "tecdar-ur"
    reader_name = "ur-link"
    child = staticmethod(child_main)

    def __init__(self, settings: UrLinkSettings):
        super().__init__(settings, settings.connect_timeout_s)
        self.ur_state: UrState | None = None       # the newest controller state, as read (its base frame)
        self._seq = 0
        self._sync = SlewClock()
        self.refused: str | None = None             # the controller refuses commands (since this one), or None
        self.identity: dict = {}                    # the controller's arm type and version (controller_identity)

    def _no_answer(self, timeout_s: float) -> str:
        return f"robot.ur.host: no UR controller answered at {self.settings.host} within {timeout_s:g} s"

    def _ended(self, exitcode) -> str:
        return f"robot.ur.host: the link to {self.settings.host} ended at start (exit code {exitcode})"

    def _refused(self, reason: str) -> str:
        return f"robot.ur.host: {self.settings.host} refused the link: {reason}"

    def _no_state(self) -> str:
        return f"no state from {self.settings.host} yet"

    def _not_running(self) -> str:
        return f"the link to {self.settings.host} is not running"

    def _ready(self, payload: tuple) -> None:
        self.identity = payload[0] or {}

    def _handle(self, msg: tuple) -> None:
        if msg[0] == "state":
            st: UrState = msg[1]
            self._sync.add(st.controller_t, st.rx_t)
            self._seq += 1
            self.ur_state = st
            self._publish(self._joint_state(st))
        elif msg[0] == "refused":
            self.refused = f"the controller refused {msg[1]}"
        elif msg[0] == "accepted":
            self.refused = None

    def _gone(self) -> None:
        if self.fault is None:
            self.fault = f"the link to {self.settings.host} has gone"

    def _joint_state(self, st: UrState) -> JointState:
        """A controller state as the daemon's: its clock, and the TCP's pose (a matrix), twist and force."""
        pose = np.eye(4)
        pose[:3, :3] = pin.exp3(np.array(st.tcp_pose[3:]))        # a rotation vector
        pose[:3, 3] = st.tcp_pose[:3]
        return JointState(t=float(self._sync.to_host(st.controller_t)), q=np.array(st.q), qd=np.array(st.qd),
                          seq=self._seq, tcp_twist=np.array(st.tcp_speed), tcp_force=np.array(st.tcp_force[:3]),
                          tcp_torque=np.array(st.tcp_force[3:6]), wrench_source="actual_TCP_force",
                          tcp_pose=pose)

    # -- RobotControl ---------------------------------------------------------
    def command_joint_velocity(self, qd: np.ndarray) -> None:
        self._send(("speedj", tuple(float(x) for x in joint_rates(qd, NQ))))

    def hold(self) -> None:
        """Bring the arm to rest and keep it there: speedJ of zeros, sent every tick like any command
        (it feeds the controller's watchdog, where speedStop would not)."""
        self._send(("speedj", (0.0,) * NQ))

    def reupload(self) -> None:
        """Upload ur-rtde's control script again (after a protective stop has been unlocked)."""
        self._send(("reupload",))
