"""`recover` on a UR: read what holds the arm (the robot mode and the safety mode, not only an error flag), clear what
the dashboard server may clear, and say what only a person may.

- A protective stop: unlocked through the dashboard server (port 29999) once the controller allows it, 5 s after
  the stop (UR's rule: the dashboard answers "Cannot unlock protective stop until 5s after occurrence"), then its
  popup closed. The link's supervisor uploads ur-rtde's control script again once the arm runs.
- An arm powered off, or on with its brakes held: powered on and its brakes released only with
  `robot.ur.allow_power_on: true` (the arm moves as its brakes release); otherwise a person does it on the pendant.
- An emergency stop, a safeguard stop, a safety violation or fault: never cleared by software; `recover` says
  which, and what a person must do.

Written from UR's dashboard server manual (e-Series 5.x, CB3 3.x) and ur-rtde's DashboardClient; tested against
tests/fakes/fake_ur.py, never on a real controller."""
from __future__ import annotations

import logging
import time

from tecdard.robots.backend import Recovery
from tecdard.robots.ur_link import ROBOT_MODE_RUNNING

log = logging.getLogger("tecdar.ur")

ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE = 3, 4, 5
SAFETY_SAFEGUARD_STOPS = {5: "a safeguard stop", 12: "an automatic-mode safeguard stop"}
SAFETY_FAULTS = {8: "a safety violation", 9: "a safety fault"}
POLL_S = 0.1
UNLOCK_RETRY_S = 0.5            # the 5 s rule: asked again this often until the controller allows it
DASHBOARD_TIMEOUT_MS = 2000
# the faults of UrBackend.faults() that `recover` may clear (robot_not_running: with allow_power_on, or the
# powered arm's own return to running; robot_program: the script is uploaded again once the arm runs)
RECOVERABLE = frozenset({"robot_protective_stop", "robot_not_running", "robot_program"})


def recover_ur(backend, timeout_s: float) -> Recovery:
    """The UR backend's `recover` (UrBackend.recover), within `timeout_s`."""
    link, host = backend.link, backend.settings.host
    deadline = time.monotonic() + timeout_s
    if link.exited.is_set() or link.fault:
        return Recovery(False, (), f"the link to the UR controller {host} is down ({link.fault or 'not connected'}): "
                                   "the daemon reconnects by itself; check the controller and the network")
    st = link.ur_state
    if st is None:
        return Recovery(False, (), f"no state from the UR controller {host} yet")
    person = _person_only(st)
    if person:
        return Recovery(False, (), person)
    if not backend.faults():
        return Recovery(True, ("the arm reports no fault: nothing to recover",))
    import dashboard_client
    db = dashboard_client.DashboardClient(host)
    steps: list[str] = []
    try:
        db.connect(DASHBOARD_TIMEOUT_MS)
    except Exception as exc:
        return Recovery(False, (), f"the UR dashboard server at {host}:29999 did not answer ({_line(exc)}): unlock "
                                   "and power the arm on the pendant")
    try:
        if st.protective_stopped:
            problem = _unlock(db, deadline, steps)
            if problem:
                return Recovery(False, tuple(steps), problem)
        problem = _power(db, backend, deadline, steps)
        if problem:
            return Recovery(False, tuple(steps), problem)
        # the supervisor uploads the control script again once the arm runs (UrBackend._supervise)
        while time.monotonic() < deadline:
            if not backend.faults():
                steps.append("the control script runs again")
                return Recovery(True, tuple(steps))
            time.sleep(POLL_S)
        code, message = next(iter(backend.faults().items()))
        return Recovery(False, tuple(steps), f"still {code} after {timeout_s:g} s: {message}")
    finally:
        try:
            db.disconnect()
        except Exception:
            pass


def _person_only(st) -> str:
    """What holds the arm that only a person may clear, or ""."""
    if st.emergency_stopped:
        return "an emergency stop holds: release the button (the pendant's or an external one), then `recover` again"
    if st.safety_mode in SAFETY_FAULTS:
        return (f"{SAFETY_FAULTS[st.safety_mode]} holds (safety mode {st.safety_mode}): restart the safety system "
                "from the pendant")
    if st.safety_mode in SAFETY_SAFEGUARD_STOPS:
        return (f"{SAFETY_SAFEGUARD_STOPS[st.safety_mode]} holds: reset the safeguard (a door, a light curtain), "
                "then `recover` again")
    return ""


def _unlock(db, deadline: float, steps: list) -> str:
    """Unlock the protective stop once the controller allows it, and close its popup; "" or why not."""
    waited = False
    while True:
        try:
            db.unlockProtectiveStop()
            break
        except Exception as exc:          # ur-rtde raises on any answer but "Protective stop releasing"
            text = _line(exc)
            if "5s" not in text and "5 s" not in text:
                return f"the controller refused to unlock the protective stop ({text}): unlock it on the pendant"
            if time.monotonic() + UNLOCK_RETRY_S > deadline:
                return "the controller did not allow the unlock in time (UR's 5 s rule): `recover` again"
            waited = True
            time.sleep(UNLOCK_RETRY_S)
    steps.append("unlocked the protective stop (dashboard server" + (", after UR's 5 s rule)" if waited else ")"))
    try:
        db.closeSafetyPopup()
        steps.append("closed the safety popup")
    except Exception as exc:
        log.info("recover: closing the safety popup failed: %s", _line(exc))
    return ""


def _power(db, backend, deadline: float, steps: list) -> str:
    """Power the arm on and release its brakes where it needs it and the config allows; "" or why not."""
    link = backend.link
    mode = _mode_settled(link, deadline)
    if mode == ROBOT_MODE_RUNNING:
        return ""
    if mode not in (ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE):
        return f"the arm is in robot mode {mode}, which `recover` does not handle: bring it to running on the pendant"
    what = "powered off" if mode == ROBOT_MODE_POWER_OFF else "powered on with its brakes held"
    if not backend.settings.allow_power_on:
        return (f"the arm is {what}: power it on and release its brakes on the pendant, or set "
                "robot.ur.allow_power_on: true to let `recover` do it")
    if mode == ROBOT_MODE_POWER_OFF:
        db.powerOn()
        steps.append("powered the arm on (dashboard server)")
        if not _wait_mode(link, (ROBOT_MODE_IDLE,), deadline):
            return "the arm did not reach idle after power on: check it on the pendant"
    db.brakeRelease()
    steps.append("released the brakes (dashboard server)")
    if not _wait_mode(link, (ROBOT_MODE_RUNNING,), deadline):
        return "the arm did not reach running after the brake release: check it on the pendant"
    return ""


def _mode_settled(link, deadline: float) -> int:
    """The robot mode once an unlock has taken effect (a protective stop's mode changes within a few cycles)."""
    end = min(deadline, time.monotonic() + 1.0)
    while time.monotonic() < end:
        st = link.ur_state
        if st is not None and not st.protective_stopped:
            return st.robot_mode
        time.sleep(POLL_S)
    return link.ur_state.robot_mode


def _wait_mode(link, modes: tuple, deadline: float) -> bool:
    while time.monotonic() < deadline:
        st = link.ur_state
        if st is not None and st.robot_mode in modes:
            return True
        time.sleep(POLL_S)
    return False


def _line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
