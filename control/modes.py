"""The control loop's mode, and the one function that changes it."""
from __future__ import annotations

import enum


class Mode(enum.Enum):
    IDLE = "idle"            # no task; the arm held
    BUSY = "busy"            # a task runs
    SETTLING = "settling"    # a task has ended (done, failed, cancelled): braking to rest
    STOPPING = "stopping"    # braking to rest after `stop` or a protective stop

    @property
    def braking(self) -> bool:
        return self in (Mode.SETTLING, Mode.STOPPING)

    def published(self, faulted: bool) -> str:
        """The `mode` of the state message (docs/zenoh-api.md): idle, busy, stopped or fault. A task
        that has ended is still `busy` while the arm brakes; an idle daemon with a fault is `fault`."""
        if self is Mode.STOPPING:
            return "stopped"
        if self is Mode.IDLE:
            return "fault" if faulted else "idle"
        return "busy"


class Event(enum.Enum):
    START = "start"          # a task was accepted
    END = "end"              # the task ended by itself, or was cancelled
    STOP = "stop"            # `stop`, a protective stop, or the daemon shutting down
    AT_REST = "at_rest"      # the brake has brought the arm to rest
    RESET = "reset"          # a failed tick: the arm was held, whatever it was doing


class TransitionError(RuntimeError):
    """An event that cannot happen in this mode (a bug of the caller)."""


_TABLE = {
    (Mode.IDLE, Event.START): Mode.BUSY,
    (Mode.BUSY, Event.END): Mode.SETTLING,
    (Mode.BUSY, Event.STOP): Mode.STOPPING,
    (Mode.IDLE, Event.STOP): Mode.STOPPING,
    (Mode.SETTLING, Event.STOP): Mode.STOPPING,
    (Mode.STOPPING, Event.STOP): Mode.STOPPING,
    (Mode.SETTLING, Event.AT_REST): Mode.IDLE,
    (Mode.STOPPING, Event.AT_REST): Mode.IDLE,
}


def transition(mode: Mode, event: Event) -> Mode:
    """The mode after `event`; TransitionError for an event the mode does not allow. RESET goes to
    IDLE from anywhere (the arm was held by the caller)."""
    if event is Event.RESET:
        return Mode.IDLE
    try:
        return _TABLE[(mode, event)]
    except KeyError:
        raise TransitionError(f"mode {mode.value}: no transition on {event.value}") from None
