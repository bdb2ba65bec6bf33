"""`robot.backend: ur`: a Universal Robots arm through ur-rtde (robots.ur_link), the fingertip board on serial.

Reads `robot.ur`:
- `host` (required): the controller's address;
- `frequency_hz`: the RTDE rate, default the controller's own (500 Hz e-Series, 125 Hz CB3);
- `accel_rad_s2`: speedJ's joint acceleration bound (default 4.0): a ceiling above the joint
  accelerations the jerk-limited Cartesian plan asks (docs/ur.md);
- `connect_timeout_s`: a controller that does not answer within this is an error (default 10);
- `watchdog_hz`: the controller's RTDE watchdog (default 10): it stops the arm when the daemon
  writes less often, so a stalled daemon never leaves the arm at its last speed.

The controller's pose, speed and force are the daemon's (a UR arm's world is its controller's base
frame, robots.model): its pose carries the arm's own calibration. Grip force: UR's RTDE carries no
gripper state (grippers speak their own protocols), so eta's schedule uses estimator.grip_force_n.

The controller's faults are the daemon's: a protective or emergency stop, a robot not running, the
control script not running (remote control off, stopped from the pendant), or a lost link each hold
as a fault (a protective stop of the task, tasks refused) until they clear. A lost link is
reconnected with back-off. When a protective stop has been unlocked, the control script is
uploaded again and told zeros at once (the controller's registers still hold the last speedJ from
before the stop); the task it served already ended on the stop.
"""
from __future__ import annotations

import logging
import socket

from tecdard.host import Check
from tecdard.options import read_options
from tecdard.robots.backend import LinkBackend, rig_section
from tecdard.robots.backends import BackendContext
from tecdard.robots.ur_link import ROBOT_MODE_RUNNING, UrLink, UrLinkError, UrLinkSettings, controller_identity
from tecdard.robots.ur_recover import RECOVERABLE, recover_ur

log = logging.getLogger("tecdar.ur")

UR_MODELS = ("ur3", "ur5", "ur10", "ur3e", "ur5e", "ur10e", "ur16e")   # CB3 (URDFs) and e-Series (robots/ur_dh.py)
E_SERIES_MAJOR = 5                      # PolyScope 5 runs e-Series arms, 3 the CB3 ones
FIRST_STATE_S = 2.0
CHECK_TIMEOUT_S = 1.0                   # `tecdard doctor`: a port that does not answer within this is closed


class UrBackend(LinkBackend):
    """The robot (receive and control, as any backend) on a UrLink; the IMU is the serial board."""

    log = log
    name = "ur"
    recoverable = RECOVERABLE

    def __init__(self, ctx: BackendContext):
        section = rig_section(ctx, "ur", UR_MODELS, "UR", "the controller's address")
        self.settings = read_options(UrLinkSettings, section, command_time_s=ctx.tick_s)
        if self.settings.watchdog_hz > 0.5 / ctx.tick_s:
            raise section.error("watchdog_hz", f"{self.settings.watchdog_hz:g} Hz would stop the arm between two control "
                                               f"ticks ({ctx.tick_s * 1e3:g} ms); at most {0.5 / ctx.tick_s:g} Hz")
        self._attach(ctx, UrLink(self.settings), f"UR controller {self.settings.host}")

    # -- lifecycle ----------------------------------------------------------------
    def start(self) -> None:
        """Connect (UrLinkError naming the host if the controller does not answer, or if it runs
        another arm than robot.model), then watch the link."""
        self.link.start()
        try:
            self._check_model(self.link.identity)
        except UrLinkError:
            self.link.stop()
            raise
        self._check_kinematics()
        self._supervise_in_background("ur-supervisor")

    def _check_model(self, identity: dict) -> None:
        """robot.model against the arm the controller's dashboard reports: its type (UR5 for a UR5
        or a UR5e) and its series (PolyScope 5: e-Series). Unknown (no dashboard): said, not refused."""
        if not identity.get("model") or not identity.get("version"):
            log.warning("robot.model: the controller at %s did not say which arm it runs (dashboard server); "
                        "check that robot.model %s is the arm", self.settings.host, self.model.name)
            return
        theirs = expected_controller_arm(identity)
        if theirs.lower() != self.model.name:
            series = "e-Series" if theirs.endswith("e") else "CB3"
            raise UrLinkError(f"robot.model: {self.model.name}, but the controller at {self.settings.host} runs a "
                              f"{theirs} ({series}, software {identity['version']}); set robot.model: {theirs.lower()}")

    def _check_kinematics(self) -> None:
        """Compare our FK of the controller's joints with the TCP the controller reports. The
        controller's carries the arm's own kinematic calibration and its TCP setting; generic URDF
        kinematics, or a tool offset that differs from the controller's TCP, put ours elsewhere.

        The controller's pose is the one the daemon uses (estimator, tasks, servo feedback): it is
        where the tool really is, to the arm's calibration (UR states about 0.1 mm of repeatability;
        nominal kinematics are millimetres off on a real arm). Our model only turns the commanded
        TCP twist into joint rates, where a millimetre-level error changes the rate by a fraction of
        a percent and the position feedback removes it. A tool offset or model that disagrees with
        the controller puts the IMU's lever arm in the wrong place, so it is said here."""
        js = self.link.wait_state(-1, FIRST_STATE_S)
        self._say_fk_offset(js.q, js.tcp_pose, "the one the controller reports",
                            "the controller's TCP setting and arm type")

    def _supervise(self) -> None:
        """Reconnect a lost link with back-off; re-upload the control script once a stop has cleared."""
        attempt = 0
        while not self._stop.wait(0.05):
            link = self.link
            if link.exited.is_set():
                attempt = self._reconnect(attempt)
                if attempt is None:
                    return
                continue
            st = link.ur_state
            if st is not None and not st.program_running and not st.protective_stopped \
                    and not st.emergency_stopped and st.robot_mode == ROBOT_MODE_RUNNING:
                link.reupload()
                self._stop.wait(1.0)          # the script starts within a few controller cycles

    def faults(self) -> dict[str, str]:
        """The controller's faults that hold now, code -> message (the daemon's `fault` events)."""
        out = {}
        link = self.link
        if link.exited.is_set() or link.fault:
            out["robot_link"] = f"UR controller {self.settings.host}: {link.fault or 'not connected'}"
        if link.refused:
            out["robot_refused"] = f"UR controller {self.settings.host}: {link.refused}"
        st = link.ur_state
        if st is None:
            return out
        if st.emergency_stopped:
            out["robot_emergency_stop"] = "the UR controller reports an emergency stop"
        elif st.protective_stopped:
            out["robot_protective_stop"] = ("the UR controller reports a protective stop: inspect its cause, "
                                            "then `recover` (or unlock it on the pendant)")
        elif st.robot_mode != ROBOT_MODE_RUNNING:
            out["robot_not_running"] = f"the UR arm is not running (robot mode {st.robot_mode})"
        elif not st.program_running:
            out["robot_program"] = ("ur-rtde's control script is not running on the controller (remote control "
                                    "off, or stopped from the pendant)")
        return out


    def recover(self, timeout_s: float):
        """Unlock a protective stop (after UR's 5 s rule), power on and release the brakes where allowed, or say
        what a person must do (robots/ur_recover.py)."""
        return recover_ur(self, timeout_s)

    def checks(self) -> list[Check]:
        """The controller's ports, its arm against robot.model, and remote control."""
        return check_ur_controller(self.settings.host, self.model.name)


def expected_controller_arm(identity: dict) -> str:
    """The arm a controller runs, as robot.model spells it but for case (UR5e), from its dashboard's
    model (UR5 for a UR5 or a UR5e) and software version (PolyScope 5: e-Series)."""
    e_series = int(identity["version"].split(".")[0]) >= E_SERIES_MAJOR
    return identity["model"].upper() + ("e" if e_series else "")


DASHBOARD_BANNER = "Connected: Universal Robots Dashboard Server"    # the dashboard's first line, CB3 and e-Series


def dashboard_banner(host: str, port: int = 29999) -> str:
    """The first line the dashboard server sends on a new connection ("" if none within the timeout)."""
    try:
        with socket.create_connection((host, port), timeout=CHECK_TIMEOUT_S) as s:
            s.settimeout(CHECK_TIMEOUT_S)
            data = b""
            while b"\n" not in data and len(data) < 256:
                chunk = s.recv(256)
                if not chunk:
                    break
                data += chunk
    except OSError:
        return ""
    return data.split(b"\n")[0].decode("utf-8", "replace").strip()


def check_ur_controller(host: str, model: str) -> list[Check]:
    """A UR controller at `host`: its dashboard, RTDE and script ports answer, it runs the arm
    robot.model names, and it is in remote control (ur-rtde uploads its script only then)."""
    ports = {"dashboard": 29999, "script": 30003, "RTDE": 30004}
    closed = []
    for name, port in ports.items():
        try:
            with socket.create_connection((host, port), timeout=CHECK_TIMEOUT_S):
                pass
        except OSError as exc:
            closed.append(f"{name} {port}: {exc.strerror or exc}")
    if closed:
        return [Check(f"UR controller {host}", "fail", "; ".join(closed),
                      "check robot.ur.host, the network to the controller, and that it is switched on")]
    banner = dashboard_banner(host)
    if not banner.startswith(DASHBOARD_BANNER):
        said = repr(banner[:60]) if banner else "nothing"
        return [Check(f"UR controller {host}", "fail", f"ports 29999, 30003 and 30004 accept connections, but "
                      f"29999 said {said}, not a UR dashboard's greeting",
                      "check robot.ur.host: another device or a program listens there")]
    out = [Check(f"UR controller {host}", "pass", "dashboard, script and RTDE ports answer")]
    identity = controller_identity(host)
    if not identity:
        out.append(Check("UR arm", "warn", "the dashboard did not say which arm this is",
                         f"check that robot.model {model} is the controller's arm"))
    else:
        theirs = expected_controller_arm(identity)
        ok = theirs.lower() == model
        out.append(Check("UR arm", "pass" if ok else "fail", f"{theirs}, software {identity['version']}",
                         None if ok else f"set robot.model: {theirs.lower()}"))
        if identity.get("remote_control") is False:
            out.append(Check("UR remote control", "fail", "the controller is in local control",
                             "switch the pendant to remote control (e-Series: the icon at its top right)"))
    return out
