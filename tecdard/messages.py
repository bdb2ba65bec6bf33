"""What the daemon's threads hand each other: frozen records and bounded buffers, never Zenoh objects.

A command keeps its Zenoh `Query` in the main thread under a request id; the control thread sees
only the id and answers with a `Reply` carrying it. The control thread tells the estimator what it
wants as one `EstimatorDirective` in a `LatestValue`; proprioception reaches the estimator through
a `DropOldestRing` of its own.
"""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass


@dataclass(frozen=True)
class StartTask:
    request: int          # the main thread's id of the query to answer
    verb: str             # a task verb (tecdard/verbs/)
    fields: dict          # validated, normalised fields (tecdard.commands.validate)


@dataclass(frozen=True)
class Cancel:
    request: int
    task: str | None      # the task to cancel; None: whichever runs


@dataclass(frozen=True)
class Stop:
    request: int | None   # None: nobody waits for the reply (the daemon's own shutdown)
    reason: str = "stopped by command"


@dataclass(frozen=True)
class Reply:
    request: int
    payload: dict         # the reply object, {"ok": ...}


@dataclass(frozen=True)
class EstimatorDirective:
    """What the control thread wants of the estimator, as state: the control thread replaces it
    (a LatestValue), the estimator thread applies whatever differs from what it applied last. A
    value cannot be lost the way a queued message can; a new episode number releases the contact
    episode (older onsets no longer count), and two episodes begun between two looks of the
    estimator are one release."""
    episode: int = 0                   # changes: end the contact episode (release)
    armed: bool = True                 # the onset trigger is armed
    arc_following: bool = False        # the arm follows an arc about the estimate (ContactKF.radial_var)
    bias_held: bool = False            # the tool touches outside an episode: no gyro bias tracking
    begin_t: float | None = None       # with a new episode: start it at this time without the trigger


class LatestValue:
    """A single-slot buffer: one writer replaces, readers take the newest."""

    def __init__(self, value=None):
        self._lock = threading.Lock()
        self._value = value

    def set(self, value) -> None:
        with self._lock:
            self._value = value

    def get(self):
        with self._lock:
            return self._value


class DropOldestRing:
    """A bounded single-producer/single-consumer hand-off that never blocks the producer: when the
    consumer falls behind by `capacity` items the oldest are overwritten and counted."""

    def __init__(self, capacity: int):
        self._items: collections.deque = collections.deque(maxlen=capacity)
        self.overwritten = 0

    def push(self, item) -> None:
        if len(self._items) == self._items.maxlen:
            self.overwritten += 1
        self._items.append(item)          # deque.append/popleft are atomic under the GIL

    def drain(self) -> list:
        out = []
        try:
            while True:
                out.append(self._items.popleft())
        except IndexError:
            return out
