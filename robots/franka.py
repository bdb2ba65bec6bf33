"""`robot.backend: franka`: a Franka arm (FR3, Panda) through franky (robots.franka_link), the fingertip board on serial.

Reads `robot.franka`:
- `host` (required): the robot's FCI address (the arm's, not Desk's web address where they differ);
- `realtime`: `enforce` (default; a real arm needs a PREEMPT_RT kernel and realtime limits, and
  `tecdard doctor` says whether this host has them) or `ignore` (simulation only: libfranka's
  1 kHz loop then runs without realtime priority and a real arm would stop on missed packets);
- `connect_timeout_s`: a robot that does not answer within this is an error (default 10);
- `watchdog_s`: how long franky holds a joint velocity after the daemon's last command before it
  stops the arm (default 0.06 s, three control ticks; at least two ticks, at most 0.5 s);
- `relative_dynamics_factor`: franky's scaling of the arm's joint velocity, acceleration and jerk
  limits for every motion (default 0.5);
- `state_rate_hz`: robot states handed to the daemon per second (default 500, as a UR e-Series
  gives; the robot's own are 1 kHz, and 1000 takes them all at twice the daemon's CPU for them);
- `gripper`: connect the Franka Hand (default true): its state, and the daemon's `grasp` and `release`
  (`gripper.backend: franka-hand`, robots/gripper.py), which the link's child runs on the hand's one connection;
- `grasp_force_n`: the force of a grasp made outside the daemon (Desk, a script): libfranka's gripper state
  carries the width and whether it holds, not the force, so while the hand holds this feeds eta's schedule
  until a `grasp` of the daemon's gives its own (default 20 N).

State: the arm's joints on the link's own thread at the robot's rate (about 1 kHz). The TCP is our
Pinocchio FK of the measured joints (robots.model `fr3`/`panda`, with robot.tool_offset), checked
against the robot's O_T_EE at start-up: an offset is said (franky-sim's O_T_EE is FK of the
commanded joints; a real arm's carries its own TCP setting from Desk). The external force is the
robot's O_F_ext_hat_K where it is not zero, else Jᵀ F = τ_J − g(q) with franky's model.

Faults (each a `fault` event, and a protective stop of the task):
- `robot_link`: the link is lost (the robot, its FCI or the network); reconnected with back-off;
- `robot_reflex`: a reflex or an aborted motion (libfranka's errors named);
- `robot_user_stop`: the user stop (the external activation device) is pressed;
- `robot_refused`: franky refused a command.

Recovery from a reflex is automatic, with back-off (RECOVER_S): the daemon has already ended the
task on the fault, and recover_from_errors only clears the robot's error latch; it moves nothing,
and nothing moves again until a client sends a new task. An operator would press the same button
in Desk, and a daemon that waits for one leaves an unattended cell stopped for a transient reflex.
A user stop is the operator's own act: it clears when they release the device, and the recovery
then runs as for a reflex.
"""
from __future__ import annotations

import logging
import resource
import threading
import time

import numpy as np

from tecdard.host import Check, can_set_fifo, check_rt_kernel
from tecdard.options import read_options
from tecdard.robots.backend import LinkBackend, Recovery, rig_section
from tecdard.robots.backends import BackendContext
from tecdard.robots.franka_link import FrankaLink, FrankaLinkSettings
from tecdard.robots.franka_server import LIBFRANKA_ROBOT_SERVER_VERSION, ROBOT_PORT, server_version

log = logging.getLogger("tecdar.franka")

FRANKA_MODELS = ("fr3", "panda")
RECOVER_S = (0.5, 1.0, 2.0, 4.0)        # back-off before each automatic error recovery while a reflex holds
RECOVERY_SETTLE_S = 0.5                # a recovery franky calls failed counts if the error clears within this
STALE_S = 2.0                           # no state from a running child for this long: the link is lost
                                        # (libfranka's own UDP timeout is 1 s)
CHECK_TIMEOUT_S = 1.0                   # `tecdard doctor`: the Connect reply it waits for
LIBFRANKA_RT_PRIORITY = 99              # libfranka puts its 1 kHz loop at SCHED_FIFO's highest priority
LIBFRANKA_MEMLOCK_BYTES = 100 << 20     # Franka's setup guide: `memlock 102400` (KiB) beside `rtprio 99`


class FrankaBackend(LinkBackend):
    """The robot (receive and control, as any backend) on a FrankaLink; the IMU is the serial board."""

    log = log
    name = "franka"
    recoverable = frozenset({"robot_reflex"})

    def __init__(self, ctx: BackendContext):
        section = rig_section(ctx, "franka", FRANKA_MODELS, "Franka", "the robot's FCI address")
        self.settings = read_options(FrankaLinkSettings, section, {"watchdog_s": 3.0 * ctx.tick_s})
        if self.settings.watchdog_s < 2.0 * ctx.tick_s:
            raise section.error("watchdog_s", f"{self.settings.watchdog_s} is below the minimum {2.0 * ctx.tick_s}")
        self._attach(ctx, FrankaLink(self.settings), f"Franka robot {self.settings.host}")
        self._recovering = threading.Lock()      # one error recovery at a time: the supervisor's or `recover`'s

    # -- lifecycle ----------------------------------------------------------------
    def start(self) -> None:
        """Connect (robots.franka_link.FrankaLinkError naming the host and what failed), cross-check the kinematics,
        then watch the link."""
        self.link.start()
        for note in self.link.notes:
            log.warning("robot.franka: %s", note)
        self._check_kinematics(self.link.identity)
        self._supervise_in_background("franka-supervisor")

    def _check_kinematics(self, identity: dict) -> None:
        """Our FK of the robot's joints against the O_T_EE it reports. A real arm's carries its end
        effector as set in Desk; a different robot.tool_offset, or a hand configured otherwise,
        puts the IMU's lever arm elsewhere, so the offset is said. franky-sim computes O_T_EE from
        the commanded joints, which equal the measured ones at rest."""
        self._say_fk_offset(identity["q"], np.array(identity["O_T_EE"]).reshape(4, 4, order="F"),
                            "the robot's O_T_EE", "the end effector set in Desk")

    def _supervise(self) -> None:
        """Reconnect a lost link with back-off; recover from a reflex with back-off."""
        attempt = recoveries = 0
        next_recovery = None
        while not self._stop.wait(0.05):
            link = self.link
            st = link.franka_state
            if not link.exited.is_set() and st is not None and time.monotonic() - st.rx_t > STALE_S:
                link.fault = f"no state from {self.settings.host} for {time.monotonic() - st.rx_t:.1f} s"
                link.stop()
            if link.exited.is_set() or not link.running:
                attempt = self._reconnect(attempt)
                if attempt is None:
                    return
                recoveries = 0
                continue
            if not link.robot_fault:
                recoveries, next_recovery = 0, None
                continue
            now = time.monotonic()
            if next_recovery is None:
                # the first recovery waits the first back-off too: the daemon's control tick has
                # seen the fault and stopped the task by then
                next_recovery = now + RECOVER_S[0]
            if now < next_recovery or "UserStopped" in link.robot_fault:
                continue
            fault = link.robot_fault
            with self._recovering:                 # never beside a `recover` the daemon was asked for
                ok, why = link.recover()
            recoveries += 1
            deadline = time.monotonic() + RECOVERY_SETTLE_S
            while not ok and link.robot_fault and time.monotonic() < deadline and not self._stop.wait(0.02):
                pass
            ok = ok or not link.robot_fault   # franky may answer from a state read before the robot's next
            if ok:
                log.info("recovered from %s", fault)
            else:
                log.warning("error recovery %d on %s failed: %s", recoveries, self.settings.host, why)
            next_recovery = time.monotonic() + RECOVER_S[min(recoveries, len(RECOVER_S) - 1)]

    def recover(self, timeout_s: float) -> Recovery:
        """franky's error recovery now (the supervisor's own waits its back-off), then the robot's mode read back: a
        robot that stays in Reflex without an error is said as such (libfranka's known case), as is a user stop."""
        link, host = self.link, self.settings.host
        if link.exited.is_set() or link.fault:
            return Recovery(False, (), f"the link to the Franka robot {host} is down ({link.fault or 'not connected'}): "
                                       "the daemon reconnects by itself; check the robot, Desk's FCI and the network")
        fault = link.robot_fault
        if not fault:
            return Recovery(True, ("the robot reports no fault: nothing to recover",))
        if "UserStopped" in fault:
            return Recovery(False, (), "the user stop is pressed: release it (the recovery then runs by itself)")
        deadline = time.monotonic() + timeout_s
        with self._recovering:
            ok, why = link.recover(max(min(timeout_s, 5.0), 0.1))
        steps = (f"franky's error recovery (recover_from_errors) on {fault}",)
        while link.robot_fault and time.monotonic() < deadline:
            time.sleep(0.02)
        st = link.franka_state
        if not link.robot_fault:
            return Recovery(True, steps + (f"the robot reads back mode {st.mode if st else '?'}, no error",))
        if st is not None and st.mode == "Reflex" and not st.errors:
            return Recovery(False, steps, "the robot stays in Reflex without an error after the recovery (a known "
                                          "libfranka case): press and release the user stop, then `recover`; if it "
                                          "stays, restart the arm from Desk")
        return Recovery(False, steps, f"the recovery did not clear it ({why or link.robot_fault}): see Desk")

    def checks(self) -> list[Check]:
        """This host's real-time fitness for robot.franka.realtime, and the robot's FCI and server version."""
        return check_franka_realtime(self.settings.realtime) + check_franka_robot(self.settings.host)

    def faults(self) -> dict[str, str]:
        """The robot's faults that hold now, code -> message (the daemon's `fault` events)."""
        out = {}
        link = self.link
        host = self.settings.host
        if link.exited.is_set() or link.fault:
            out["robot_link"] = f"Franka robot {host}: {link.fault or 'not connected'}"
            return out
        fault = link.robot_fault
        if not fault:
            return out
        if "UserStopped" in fault:
            out["robot_user_stop"] = (f"Franka robot {host}: the user stop is pressed; release it to go on "
                                      f"(the error recovery then runs by itself)")
        elif fault.startswith("velocity command") or fault.startswith("hold"):
            out["robot_refused"] = f"Franka robot {host} refused a command: {fault}"
        else:
            out["robot_reflex"] = (f"Franka robot {host}: {fault}; recovering by itself (franky's "
                                   f"recover_from_errors; `recover` runs it now), then a new task may run")
        return out


def check_franka_realtime(realtime: str, sys_realtime: str = "/sys/kernel/realtime", version: str | None = None,
                          memlock: tuple[int, int] | None = None) -> list[Check]:
    """Whether this host is fit for robot.franka.realtime: enforce. libfranka then refuses to
    connect without a real-time kernel (franky's RealtimeException), raises its control thread to
    SCHED_FIFO 99 and locks its memory; a real arm stops with communication_constraints_violation
    when its 1 kHz packets come late."""
    if realtime != "enforce":
        return [Check("Franka realtime", "warn", "robot.franka.realtime: ignore: libfranka's 1 kHz loop runs "
                      "without real-time priority; right for franky-sim, not for a real arm",
                      "set realtime: enforce beside a real arm, on a host this doctor passes")]
    kernel = check_rt_kernel(sys_realtime, version)
    out = [Check("Franka realtime kernel", "pass" if kernel.status == "pass" else "fail",
                 kernel.detail + ("" if kernel.status == "pass" else ": franky refuses to connect with realtime: "
                                  "enforce (RealtimeException)"), kernel.fix)]
    problem = can_set_fifo(LIBFRANKA_RT_PRIORITY)
    out.append(Check("Franka SCHED_FIFO 99", "pass" if problem is None else "fail",
                     "libfranka's control thread can run at SCHED_FIFO 99" if problem is None else problem,
                     "`@realtime - rtprio 99` in /etc/security/limits.d/franka.conf with this user in group "
                     "realtime, or LimitRTPRIO=99 in the unit"))
    soft, hard = memlock or resource.getrlimit(resource.RLIMIT_MEMLOCK)
    ok = soft == resource.RLIM_INFINITY or soft >= LIBFRANKA_MEMLOCK_BYTES
    shown = "unlimited" if soft == resource.RLIM_INFINITY else f"{soft >> 10} KiB"
    out.append(Check("Franka memlock", "pass" if ok else "warn", f"RLIMIT_MEMLOCK {shown}",
                     None if ok else "`@realtime - memlock 102400` in /etc/security/limits.d/franka.conf, or "
                     "LimitMEMLOCK=infinity in the unit"))
    return out


def check_franka_robot(host: str, timeout_s: float = CHECK_TIMEOUT_S) -> list[Check]:
    """A Franka robot at `host`: its FCI answers libfranka's Connect with the robot server version
    this franky speaks."""
    try:
        status, version = server_version(host, timeout_s)
    except ConnectionRefusedError:
        return [Check(f"Franka robot {host}", "fail", f"port {ROBOT_PORT} refused the connection",
                      "enable FCI in Desk (and open the brakes), and check robot.franka.host")]
    except (OSError, ValueError) as exc:
        return [Check(f"Franka robot {host}", "fail", f"no Connect reply on port {ROBOT_PORT}: "
                      f"{getattr(exc, 'strerror', None) or exc or type(exc).__name__}",
                      "check robot.franka.host, the network to the robot, and that FCI is enabled")]
    if status != 0 or version != LIBFRANKA_ROBOT_SERVER_VERSION:
        return [Check(f"Franka robot {host}", "fail", f"robot server version {version}; this franky (libfranka "
                      f"0.21.2) speaks {LIBFRANKA_ROBOT_SERVER_VERSION}",
                      "install the franky-control release built for the robot's system version, or update the "
                      "robot")]
    return [Check(f"Franka robot {host}", "pass", f"robot server version {version}, as this franky speaks")]
