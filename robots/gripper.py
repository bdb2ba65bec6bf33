"""The gripper that holds the object: `gripper.backend` (docs/gripper.md).

Every task starts with the object held at a grip force, and eta, the fingertip's transmission, is looked up by
that force. A gripper here closes and opens on command (`tecdard grasp --force N`, `tecdard release`) and says
what it holds: its opening, its force and whether it has grasped something, and where the force comes from:

- `measured`: the gripper reports the force it exerts (none of ours does yet);
- `commanded`: the force it was told to grasp with (the Franka Hand through franky, a Robotiq 2F-85/140 through
  its URCap's socket, the simulator's hand);
- `assumed`: nobody told the daemon (`manual`: a person grasps; the config or the command gives the force).

`grasp` and `release` block until the fingers stop (at most `gripper.timeout_s`), so the daemon calls them on a
thread of its own (runtime/gripper_worker.py); `state` never blocks.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace

from tecdard.options import option, read_options

MEASURED, COMMANDED, ASSUMED = "measured", "commanded", "assumed"
BACKENDS = ("auto", "none", "manual", "sim", "franka-hand", "robotiq")


class GripperError(Exception):
    """The gripper refused, failed or did not answer; the message is one line naming which and why."""


@dataclass(frozen=True)
class GripState:
    """What the gripper says now."""
    width_m: float | None = None          # the fingers' opening (None: it cannot say)
    force_n: float | None = None          # the grip force while it holds (None: not holding, or unknown)
    grasped: bool | None = None           # it holds something (None: it cannot say: `manual`)
    force_source: str = ASSUMED           # measured | commanded | assumed
    moving: bool = False
    fault: str = ""                       # the gripper's own fault, "" when none

    def to_json(self, kind: str) -> dict:
        return {"kind": kind, "width_m": _rounded(self.width_m, 5), "force_n": _rounded(self.force_n, 2),
                "grasped": self.grasped, "force_source": self.force_source, "moving": self.moving,
                "fault": self.fault or None}


def _rounded(x: float | None, digits: int) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


@dataclass(frozen=True)
class GripperParams:
    """The `gripper` section."""
    backend: str = option("auto", "the gripper: auto (the arm's own: sim's hand, a Franka's hand; none on a UR), none, "
                                  "manual (a person grasps), sim, franka-hand, robotiq (a 2F-85/140 on a UR)",
                          choices=BACKENDS)
    force_n: float = option(30.0, "the grip force a grasp uses when the command gives none (manual: the force "
                                  "assumed); eta is looked up by it", unit="N", above=0.0, maxval=300.0)
    max_force_n: float = option(140.0, "the largest grip force a command may ask for", unit="N", above=0.0,
                                maxval=300.0)
    speed_m_s: float = option(0.02, "the fingers' closing and opening speed", unit="m/s", above=0.0, maxval=0.2)
    width_m: float = option(0.005, "the object's width between the fingers: a grasp that closes to less than "
                                   "width - 4 mm holds nothing (Franka Hand)", unit="m", minval=0.0, maxval=0.15)
    open_width_m: float = option(0.08, "the opening a release moves to (Franka Hand; a Robotiq opens fully)",
                                 unit="m", minval=0.0, maxval=0.15)
    timeout_s: float = option(5.0, "a grasp or release that has not finished within this is an error", unit="s",
                              above=0.0, maxval=30.0)
    robotiq_host: str = option("", "the UR controller whose Robotiq URCap serves the gripper (default: robot.ur.host)",
                               max_len=253)
    robotiq_port: int = option(63352, "the URCap's socket", minval=1, maxval=65535)
    robotiq_model: str = option("2f-85", "the Robotiq gripper: its stroke and force range", choices=("2f-85", "2f-140"))

    @classmethod
    def from_config(cls, section) -> "GripperParams":
        p = read_options(cls, section)
        if p.force_n > p.max_force_n:
            raise section.error("force_n", f"{p.force_n:g} N is above max_force_n {p.max_force_n:g} N")
        return p


class Gripper:
    """A gripper the daemon drives. `kind` names it in `state`; `reports_grasp` says whether `grasped` means
    anything (a task refuses to start when such a gripper holds nothing)."""

    kind = "none"
    reports_grasp = False

    def grasp(self, force_n: float, width_m: float, speed_m_s: float, timeout_s: float) -> GripState:
        raise NotImplementedError

    def release(self, width_m: float, speed_m_s: float, timeout_s: float) -> GripState:
        raise NotImplementedError

    def state(self) -> GripState:
        raise NotImplementedError

    def stop(self) -> None:
        """Stop the fingers where they are (the daemon's `stop`); never blocks for long, never raises."""

    def close(self) -> None:
        """Release the connection (not the object)."""


class ManualGripper(Gripper):
    """A person grasps and releases; the daemon only records the force it is told. `grasp --force N` says a
    person has grasped at N (the config's `gripper.force_n` until then); `release` says they let go."""

    kind = "manual"

    def __init__(self, force_n: float):
        self._state = GripState(force_n=force_n, force_source=ASSUMED)

    def grasp(self, force_n, width_m, speed_m_s, timeout_s) -> GripState:
        self._state = GripState(force_n=force_n, force_source=ASSUMED)
        return self._state

    def release(self, width_m, speed_m_s, timeout_s) -> GripState:
        self._state = GripState(force_source=ASSUMED)
        return self._state

    def state(self) -> GripState:
        return self._state


class SimGripper(Gripper):
    """The simulator's hand: the simulated object starts held, at the configured force. `release` lets it go
    (the simulated world is gone until a grasp); `grasp` takes a fresh one at the TCP."""

    kind = "sim"
    reports_grasp = True

    def __init__(self, world, force_n: float, width_m: float = 0.025):
        self.world, self.width_m = world, width_m
        self._state = GripState(width_m=width_m, force_n=force_n, grasped=True, force_source=COMMANDED)

    def grasp(self, force_n, width_m, speed_m_s, timeout_s) -> GripState:
        if not self._state.grasped:
            self.world.rebuild()
        self._state = GripState(width_m=self.width_m, force_n=force_n, grasped=True, force_source=COMMANDED)
        return self._state

    def release(self, width_m, speed_m_s, timeout_s) -> GripState:
        if self._state.grasped:
            self.world.let_go()
        self._state = GripState(width_m=width_m, grasped=False, force_source=COMMANDED)
        return self._state

    def state(self) -> GripState:
        return self._state


class FrankaHand(Gripper):
    """The Franka Hand through franky's Gripper, on the Franka backend's link (the robot's child process owns
    the hand's one connection: robots/franka_link.py). The hand reports its opening and whether it holds
    (libfranka's is_grasped: the opening within the grasp's tolerances); not its force: the force is the
    grasp's command."""

    kind = "franka-hand"
    reports_grasp = True
    EPSILON_INNER_M = 0.004          # closing past width - 4 mm: nothing between the fingers
    EPSILON_OUTER_M = 0.1            # any object wider than width, up to the hand's stroke, is held

    def __init__(self, link):
        self.link = link
        self._force_n: float | None = None

    def grasp(self, force_n, width_m, speed_m_s, timeout_s) -> GripState:
        ok, why = self.link.grip(("grasp", width_m, speed_m_s, force_n, self.EPSILON_INNER_M, self.EPSILON_OUTER_M),
                                 timeout_s)
        if why:
            raise GripperError(f"Franka Hand: the grasp failed: {why}")
        self._force_n = force_n if ok else None
        return replace(self.state(), grasped=ok, force_n=self._force_n)

    def release(self, width_m, speed_m_s, timeout_s) -> GripState:
        ok, why = self.link.grip(("move", width_m, speed_m_s), timeout_s)
        if why or not ok:
            raise GripperError(f"Franka Hand: the release failed: {why or 'the hand did not reach its opening'}")
        self._force_n = None
        return replace(self.state(), grasped=False, force_n=None)

    def state(self) -> GripState:
        st = self.link.franka_state
        if st is None or st.grip_width is None:
            return GripState(force_source=COMMANDED, fault="no state from the hand")
        return GripState(width_m=st.grip_width, force_n=self._force_n if st.grasped else None, grasped=st.grasped,
                         force_source=COMMANDED)

    def stop(self) -> None:
        try:
            self.link.grip_stop()
        except Exception:                 # a link that has gone: nothing moves without it
            pass


# -- Robotiq 2F-85/140 through the URCap's socket ------------------------------------------------------------------
# Robotiq's URCap serves its gripper on the UR controller's port 63352: one ASCII command a line, `SET <VAR> <n>`
# (several pairs a line) answered `ack`, `GET <VAR>` answered `<VAR> <n>`. The variables are the gripper's
# registers (Robotiq's 2F-85/140 manual, "Control"): ACT activates, GTO goes to the request, POS/SPE/FOR are
# the position (0 open .. 255 closed), speed and force requests (0..255), STA the activation status (3 done),
# OBJ the object detection (0 moving, 1 stopped opening on an object, 2 stopped closing on an object, 3 at the
# requested position: nothing met), FLT the fault (0 none), and GET POS the fingers' position.
ROBOTIQ = {"2f-85": {"stroke_m": 0.085, "force_n": (20.0, 235.0), "speed_m_s": (0.020, 0.150)},
           "2f-140": {"stroke_m": 0.140, "force_n": (10.0, 125.0), "speed_m_s": (0.030, 0.250)}}
ROBOTIQ_POLL_S = 0.02
ROBOTIQ_ACTIVATE_S = 5.0          # activation opens and closes the fingers once: a few seconds
ROBOTIQ_REPLY_S = 1.0
OBJ_MOVING, OBJ_OPENING_ON_OBJECT, OBJ_CLOSING_ON_OBJECT, OBJ_AT_REQUEST = 0, 1, 2, 3


def _byte(x: float, lo: float, hi: float) -> int:
    """A physical request as the register's 0..255, clamped to the gripper's range."""
    return int(round(255.0 * (min(max(x, lo), hi) - lo) / (hi - lo)))


class RobotiqGripper(Gripper):
    """A Robotiq 2F-85 or 2F-140 on a UR, through the socket its URCap serves (port 63352). The force is the
    grasp's request, mapped linearly onto the model's force range (the manual gives the range, not the curve);
    the opening is the position register mapped onto the stroke (0 open, 255 closed), to a few mm."""

    kind = "robotiq"
    reports_grasp = True

    def __init__(self, host: str, port: int = 63352, model: str = "2f-85", connect_timeout_s: float = 3.0):
        import socket
        self.host, self.port, self.model = host, port, ROBOTIQ[model]
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        try:
            self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise GripperError(f"gripper.robotiq_host: no Robotiq URCap answered at {host}:{port} "
                               f"({exc.strerror or type(exc).__name__}): is the gripper's URCap installed and the "
                               f"gripper activated on the pendant?") from None
        self._sock.settimeout(ROBOTIQ_REPLY_S)
        self._buf = b""
        self._force_n: float | None = None
        self._state = GripState(force_source=COMMANDED)
        self._activate()
        self._poll()

    # -- the wire ---------------------------------------------------------------------------------
    def _ask(self, line: str) -> str:
        """One command, one reply line; GripperError on silence, a closed socket or a reply over 64 bytes."""
        with self._lock:
            try:
                self._sock.sendall(line.encode("ascii") + b"\n")
                while b"\n" not in self._buf:
                    chunk = self._sock.recv(256)
                    if not chunk:
                        raise GripperError(f"Robotiq URCap at {self.host}:{self.port} closed the connection")
                    self._buf += chunk
                    if len(self._buf) > 64:
                        raise GripperError(f"Robotiq URCap at {self.host}:{self.port}: a reply of over 64 bytes "
                                           f"to {line!r}")
            except OSError as exc:
                raise GripperError(f"Robotiq URCap at {self.host}:{self.port}: no reply to {line!r} "
                                   f"({exc.strerror or type(exc).__name__})") from None
            reply, _, self._buf = self._buf.partition(b"\n")
        return reply.decode("ascii", "replace").strip()

    def _set(self, **regs: int) -> None:
        line = "SET " + " ".join(f"{k} {int(v)}" for k, v in regs.items())
        reply = self._ask(line)
        if reply != "ack":
            raise GripperError(f"Robotiq URCap refused {line!r}: answered {reply[:40]!r}")

    def _get(self, reg: str) -> int:
        reply = self._ask(f"GET {reg}")
        name, _, value = reply.partition(" ")
        if name != reg or not value.strip().isdigit() or not 0 <= int(value) <= 255:
            raise GripperError(f"Robotiq URCap answered {reply[:40]!r} to GET {reg}")
        return int(value)

    # -- the gripper ------------------------------------------------------------------------------
    def _activate(self) -> None:
        if self._get("STA") == 3:
            return
        self._set(ACT=1)
        deadline = time.monotonic() + ROBOTIQ_ACTIVATE_S
        while self._get("STA") != 3:
            if time.monotonic() > deadline:
                raise GripperError(f"Robotiq at {self.host}: not activated within {ROBOTIQ_ACTIVATE_S:g} s "
                                   f"(fault {self._get('FLT')})")
            time.sleep(ROBOTIQ_POLL_S * 5)

    def _width(self, pos: int) -> float:
        return self.model["stroke_m"] * (1.0 - pos / 255.0)

    def _poll(self) -> GripState:
        pos, obj, flt = self._get("POS"), self._get("OBJ"), self._get("FLT")
        grasped = obj == OBJ_CLOSING_ON_OBJECT
        self._state = GripState(width_m=self._width(pos), force_n=self._force_n if grasped else None, grasped=grasped,
                                force_source=COMMANDED, moving=obj == OBJ_MOVING,
                                fault="" if flt == 0 else f"Robotiq fault {flt:#04x}")
        return self._state

    def _go(self, pos: int, speed_m_s: float, force: int, timeout_s: float) -> GripState:
        spe = _byte(speed_m_s, *self.model["speed_m_s"])
        self._stopping.clear()
        self._set(POS=pos, SPE=spe, FOR=force)
        self._set(GTO=1)
        deadline = time.monotonic() + timeout_s
        # the request is taken when PRE echoes it; from then on OBJ says whether the fingers still move
        taken = False
        while True:
            if self._stopping.is_set():
                raise GripperError("Robotiq: stopped by the daemon's stop")
            if time.monotonic() > deadline:
                raise GripperError(f"Robotiq at {self.host}: the fingers had not stopped after {timeout_s:g} s")
            taken = taken or self._get("PRE") == pos
            if taken:
                st = self._poll()
                if st.fault:
                    raise GripperError(f"Robotiq at {self.host}: {st.fault}")
                if not st.moving:
                    return st
            time.sleep(ROBOTIQ_POLL_S)

    def grasp(self, force_n, width_m, speed_m_s, timeout_s) -> GripState:
        lo, hi = self.model["force_n"]
        force = _byte(force_n, lo, hi)
        self._force_n = lo + (hi - lo) * force / 255.0         # the force the request stands for
        st = self._go(255, speed_m_s, force, timeout_s)
        if not st.grasped:
            self._force_n = None
        return self._state if st.grasped else replace(st, force_n=None)

    def release(self, width_m, speed_m_s, timeout_s) -> GripState:
        self._force_n = None
        return self._go(0, speed_m_s, 0, timeout_s)

    def state(self) -> GripState:
        try:
            return self._poll()
        except GripperError as exc:
            return replace(self._state, fault=str(exc))

    def stop(self) -> None:
        self._stopping.set()
        try:
            self._set(GTO=0)
        except GripperError:
            pass

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass


NEEDS_BACKEND = {"sim": "sim", "franka-hand": "franka"}     # a gripper that is part of one arm's backend


def gripper_kind(backend: str, robot_backend: str) -> str:
    """`gripper.backend` resolved for the arm (`auto`: the arm's own hand, none on a UR or an observed arm);
    GripperError (one line) for a gripper that is another arm's."""
    kind = {"sim": "sim", "franka": "franka-hand"}.get(robot_backend, "none") if backend == "auto" else backend
    need = NEEDS_BACKEND.get(kind)
    if need is not None and need != robot_backend:
        raise GripperError(f"gripper.backend: {kind} needs robot.backend: {need}, not {robot_backend}")
    return kind


def force_source(kind: str) -> str:
    """Where a gripper of this kind takes its grip force from (none and manual: nobody measured it)."""
    return ASSUMED if kind in ("none", "manual") else COMMANDED


def build_gripper(params: GripperParams, kind: str, backend, robot_section) -> Gripper | None:
    """The gripper of `kind` (gripper_kind's) on a started backend, or None for `none`; GripperError (one
    line) when it cannot be reached."""
    if kind == "none":
        return None
    if kind == "manual":
        return ManualGripper(params.force_n)
    if kind == "sim":
        return SimGripper(backend.world_control, params.force_n)
    if kind == "franka-hand":
        return FrankaHand(backend.link)
    return RobotiqGripper(robotiq_host(params, robot_section), params.robotiq_port, params.robotiq_model)


def robotiq_host(params: GripperParams, robot_section) -> str:
    host = params.robotiq_host or robot_section.section("ur").getstr("host", "", max_len=253)
    if not host:
        raise GripperError("gripper.robotiq_host: no host (give it, or use robot.backend: ur with robot.ur.host)")
    return host


def check_gripper(params: GripperParams, kind: str, robot_section, timeout_s: float = 1.0):
    """`tecdard doctor`'s line for the gripper: a Robotiq's URCap answers on its port and says whether the gripper
    is activated; the other kinds say what they are (a Franka Hand is reached through the arm's own check)."""
    from tecdard.host import Check
    if kind != "robotiq":
        what = {"none": "none: grasp and release are refused, the grip force is estimator.grip_force_n, assumed",
                "manual": "manual: a person grasps; the force given to `grasp` (or gripper.force_n) is assumed"}
        return Check("gripper", "pass", what.get(kind, f"{kind}: reached through the arm's backend"))
    import socket
    try:
        host = robotiq_host(params, robot_section)
        with socket.create_connection((host, params.robotiq_port), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            sock.sendall(b"GET STA\n")
            reply = sock.recv(64).decode("ascii", "replace").strip()
    except GripperError as exc:
        return Check("gripper", "fail", str(exc), "set gripper.robotiq_host")
    except OSError as exc:
        return Check("gripper", "fail", f"no Robotiq URCap answers at {host}:{params.robotiq_port} "
                                        f"({exc.strerror or type(exc).__name__})",
                     "install Robotiq's gripper URCap on the controller and activate the gripper once on the pendant")
    if reply == "STA 3":
        return Check("gripper", "pass", f"Robotiq URCap at {host}:{params.robotiq_port} answers; the gripper is activated")
    if reply.startswith("STA "):
        return Check("gripper", "warn", f"Robotiq URCap at {host}:{params.robotiq_port} answers {reply!r}: the gripper "
                                        "is not activated (the daemon activates it at start, which opens and closes it)",
                     "activate it on the pendant, with nothing between the fingers")
    return Check("gripper", "fail", f"{host}:{params.robotiq_port} answered {reply[:40]!r} to GET STA: not a Robotiq "
                                    "URCap", "check gripper.robotiq_host and robotiq_port")
