"""The main thread's pass: the control thread's replies, then the queued queries, then the telemetry."""
from __future__ import annotations

import logging
import queue
import time

from tecdard.api.session import dumps
from tecdard.runtime.intake import QueryIntake
from tecdard.runtime.messages import Outbox

log = logging.getLogger("tecdar")

TELEMETRY_PER_PASS = 64        # state, contact and event messages published per pass, then queries again


def status_json(control, intake=None, threads=None) -> str | None:
    """`status`: the control thread's newest state (at most a tick old), not the newest published
    one, which can wait behind other telemetry while replies go first; with the command intake's
    counts (`intake`: queries taken, stops, refusals, rate-limited and dropped queries) and each OS
    thread's CPU share and wake-up wait (`threads`: runtime.threads.ThreadUsage)."""
    state = control.latest_state.get()
    if state is None:
        return None
    extra = {}
    if intake is not None:
        extra["intake"] = dict(intake.counters)
    if threads is not None:
        extra["threads"] = threads.snapshot()
    return dumps({**state, **extra} if extra else state)


class FrontDoor:
    """A way in for commands and out for telemetry, which the main loop serves alike with the others: the
    Zenoh API's keys (ZenohDoor), the ROS 2 node (runtime.ros2_node.Ros2Node). Every method runs on the
    main thread; replies go back through the command intake that every door hands its requests to."""

    def poll(self, now: float) -> int:
        """Take the requests that wait (into the intake): how many."""
        return 0

    def on_telemetry(self, kind: str, body: dict, text: str) -> None:
        """One state, contact or event message (`text`: its JSON), in the order published."""

    def publish_pending(self, now: float) -> None:
        """The end of a pass: send what this door batches."""


class ZenohDoor(FrontDoor):
    """The Zenoh API (docs/zenoh-api.md): the queries on its command keys, its state, contact and events."""

    def __init__(self, intake: QueryIntake | None, pub_state, pub_contact, pub_events):
        self.intake = intake
        self.pub = {"state": pub_state, "contact": pub_contact, "event": pub_events}

    def poll(self, now: float) -> int:
        return self.intake.poll(now)

    def on_telemetry(self, kind: str, body: dict, text: str) -> None:
        self.pub[kind].put(text)          # the threads put only these three kinds


class MainLoop:
    """One pass of the main thread: the control thread's replies first, then the queued requests of
    every front door (bounded per ring), then at most TELEMETRY_PER_PASS telemetry messages to each.
    However much telemetry waits, a command's reply waits at most one pass behind it."""

    def __init__(self, intake: QueryIntake | None, control, outbox: Outbox, doors: tuple[FrontDoor, ...],
                 annotate=None, on_event=None):
        """`intake`: where every door's requests go and the replies come back. `annotate(event) -> event`:
        the backend's additions to events (the simulator's truth on a task's end), applied here on the
        main thread, never on the control tick. `on_event(event)` sees every event published (the
        recorder's)."""
        self.intake, self.control, self.outbox = intake, control, outbox
        self.doors = doors
        self.annotate = annotate
        self.on_event = on_event
        self.active_at = -float("inf")     # when a query was last taken or a reply delivered (monotonic s)

    def serve_commands(self, now: float) -> None:
        while True:
            try:
                self.intake.deliver(self.control.replies.get_nowait())
                self.active_at = now
            except queue.Empty:
                break
        for door in self.doors:
            if door.poll(now):
                self.active_at = now

    def publish_telemetry(self, wait_s: float) -> int:
        """Publish up to TELEMETRY_PER_PASS queued messages, waiting up to wait_s for the first."""
        try:
            msg = self.outbox.get(timeout=wait_s) if wait_s > 0 else self.outbox.get_nowait()
        except queue.Empty:
            self._end_pass()
            return 0
        for n in range(1, TELEMETRY_PER_PASS + 1):
            kind, body = msg[0], msg[1]
            if kind == "event" and self.annotate is not None:
                body = self._annotated(body)
            text = dumps(body)
            if kind == "event":
                log.info("event %s", text)
                if self.on_event is not None:
                    self.on_event(body)
            for door in self.doors:
                door.on_telemetry(kind, body, text)
            if n == TELEMETRY_PER_PASS:
                break
            try:
                msg = self.outbox.get_nowait()
            except queue.Empty:
                break
        self._end_pass()
        return n

    def _end_pass(self) -> None:
        now = time.monotonic()
        for door in self.doors:
            door.publish_pending(now)

    def _annotated(self, event: dict) -> dict:
        try:
            return self.annotate(event)
        except Exception:
            # an annotation is for tests and benchmarks: a failure never costs the event itself
            log.exception("annotating a %s event failed", event.get("kind"))
            return event
