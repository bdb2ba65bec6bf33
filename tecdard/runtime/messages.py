"""What the daemon's threads hand each other: frozen records and bounded buffers, never Zenoh objects.

A command keeps its Zenoh `Query` in the main thread under a request id; the control thread sees
only the id and answers with a `Reply` carrying it. The control thread tells the estimator what it
wants as one `control.pipeline.EstimatorDirective` in a `LatestValue`; proprioception reaches the
estimator through a `DropOldestRing` of its own.
"""
from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from dataclasses import dataclass

log = logging.getLogger("tecdar")

DROP_LOG_S = 1.0              # a dropped event is logged at most once this often (with the count since)


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
class Grip:
    request: int
    verb: str             # "grasp" or "release"
    fields: dict          # validated: force_n, width_m, speed_m_s (tecdard.commands.validate)


@dataclass(frozen=True)
class Recover:
    request: int          # `recover`: return the arm to a state where tasks can run (robots.backend.Recovery)


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


class Outbox:
    """The threads' telemetry for the main thread to publish: `state`, `contact` and `event` messages in
    one bounded queue that never blocks a producer. What does not fit is dropped and counted by kind
    (`dropped`, in every state message's `control.outbox_dropped`); a dropped event is also logged,
    at most one line a second with the count since the last."""

    KINDS = ("state", "contact", "event")

    def __init__(self, capacity: int):
        self._q: queue.Queue = queue.Queue(capacity)
        self.dropped = dict.fromkeys(self.KINDS, 0)
        self._lock = threading.Lock()
        self._logged_at = -float("inf")
        self._unlogged = 0

    def put(self, kind: str, body: dict) -> bool:
        """A message of `kind`; False when the outbox was full (dropped and counted)."""
        try:
            self._q.put_nowait((kind, body))
            return True
        except queue.Full:
            with self._lock:
                self.dropped[kind] += 1
            if kind == "event":
                self._log_drop(body.get("kind"))
            return False

    def event(self, kind: str, **fields) -> bool:
        """An event stamped now (monotonic s)."""
        return self.put("event", {"t": time.monotonic(), "kind": kind, **fields})

    def _log_drop(self, kind) -> None:
        now = time.monotonic()
        with self._lock:
            self._unlogged += 1
            if now - self._logged_at < DROP_LOG_S:
                return
            count, self._unlogged, self._logged_at = self._unlogged, 0, now
        log.warning("event %s dropped: the outbox is full (%d events dropped since the last such line)", kind, count)

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.dropped)

    def get(self, timeout: float | None = None):
        """The oldest (kind, body); queue.Empty after `timeout` s (None: wait)."""
        return self._q.get(timeout=timeout)

    def get_nowait(self):
        return self._q.get_nowait()

    def qsize(self) -> int:
        return self._q.qsize()

    def empty(self) -> bool:
        return self._q.empty()

    @property
    def queue(self):
        """The queued messages, oldest first (a snapshot view, for tests)."""
        return self._q.queue
