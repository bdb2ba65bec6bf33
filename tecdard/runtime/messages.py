"""What the daemon's threads hand each other: frozen records and bounded buffers, never Zenoh objects.

A command keeps its Zenoh `Query` in the main thread under a request id; the control thread sees
only the id and answers with a `Reply` carrying it. The control thread tells the estimator what it
wants as one `control.pipeline.EstimatorDirective` in a `LatestValue`; proprioception reaches the
estimator through a `DropOldestRing` of its own.
"""
from __future__ import annotations

import collections
import queue
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


class Inbox:
    """A bounded hand-over to a consumer thread that never blocks its producers: what does not fit
    is dropped and counted (the estimator thread feeding the recorder and the live view)."""

    def __init__(self, capacity: int):
        self._q: queue.Queue = queue.Queue(capacity)
        self.dropped = 0

    def put(self, item) -> bool:
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def get(self, timeout: float):
        """The oldest item, or None after `timeout` s."""
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None

    def drain(self) -> list:
        items = []
        while True:
            try:
                items.append(self._q.get_nowait())
            except queue.Empty:
                return items

    def empty(self) -> bool:
        return self._q.empty()
