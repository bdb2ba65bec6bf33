"""A Zenoh client of the `tecdar/1` API: commands, event and state streams (used by the demo, CLI and tests)."""
from __future__ import annotations

import json
import queue
import time

import zenoh

from tecdard.api.session import Keys, TlsFiles, dumps, session_config

WAIT_REPORT_S = 10.0           # wait_alive says what it waits for this often
# Until the daemon listens, a liveliness query returns at once (no route): without a pause a wait
# spun a core at ~70 000 queries a second while the daemon started on the other one.
ALIVE_POLL_S = 0.05


class ClientError(RuntimeError):
    pass


class Client:
    """Connects to a daemon's endpoint (no listening, no multicast scouting)."""

    def __init__(self, endpoint: str, robot: str = "sim", tls: TlsFiles | None = None,
                 open_timeout_s: float | None = None):
        """`tls`: this client's certificate and key and the CA, for a daemon on a tls/ endpoint.
        `open_timeout_s`: how long a transport's handshake may take (Zenoh's default, 10 s, is also
        how long closing the session waits on an endpoint that accepts TCP but never answers)."""
        self.keys = Keys(robot)
        self.session = zenoh.open(session_config([], [endpoint], tls=tls, open_timeout_s=open_timeout_s))
        self.events: queue.Queue = queue.Queue()
        self.event_log: list[dict] = []       # every event seen, in order (wait_event consumes the queue)
        self.states: queue.Queue = queue.Queue(maxsize=1000)
        self.contacts: queue.Queue = queue.Queue(maxsize=10000)
        self._subs = [
            self.session.declare_subscriber(self.keys.events, self._on_event),
            self.session.declare_subscriber(self.keys.state, lambda s: _put_latest(self.states, s)),
            self.session.declare_subscriber(self.keys.contact, lambda s: _put_latest(self.contacts, s)),
        ]

    def _on_event(self, sample) -> None:
        ev = json.loads(sample.payload.to_string())
        self.event_log.append(ev)
        self.events.put(ev)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.session.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def alive(self, timeout: float = 1.0) -> bool:
        replies = self.session.liveliness().get(self.keys.alive, timeout=timeout)
        return any(r.ok is not None for r in replies)

    def wait_alive(self, timeout: float = 30.0, running=None, waiting=None) -> None:
        """Until the daemon's liveliness token is there (it declares it once READY: its threads run
        and the IMU has warmed the onset detector). `running()` False (a daemon process that exited)
        ends the wait at once; `waiting(seconds_so_far)` is called when the first look finds no
        daemon, then every WAIT_REPORT_S, to say what is awaited."""
        t0 = time.monotonic()
        deadline, report = t0 + timeout, 0.0
        while True:
            if self.alive(0.5):
                return
            now = time.monotonic()
            if running is not None and not running():
                raise ClientError(f"the daemon exited before {self.keys.alive} came alive")
            if now >= deadline:
                raise ClientError(f"daemon {self.keys.alive} not alive after {timeout:.0f} s")
            if waiting is not None and now - t0 >= report:
                waiting(now - t0)
                report += WAIT_REPORT_S
            time.sleep(ALIVE_POLL_S)      # with no route yet a query returns at once: never spin

    def command(self, verb: str, payload: dict | str | None = None, timeout: float = 10.0) -> dict:
        """Send a command and return the decoded reply."""
        if isinstance(payload, dict):
            payload = dumps(payload)
        kwargs = {"timeout": timeout}
        if payload is not None:
            kwargs["payload"] = payload
        for reply in self.session.get(self.keys.cmd(verb), **kwargs):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_string())
            raise ClientError(f"{verb}: error reply {reply.err.payload.to_string()}")
        raise ClientError(f"{verb}: no reply within {timeout:.0f} s")

    def wait_event(self, kinds: tuple[str, ...], task: str | None = None, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ClientError(f"no {'/'.join(kinds)} event within {timeout:.0f} s")
            try:
                ev = self.events.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if ev.get("kind") in kinds and (task is None or ev.get("task") in (None, task)):
                return ev


def _put_latest(q: queue.Queue, sample) -> None:
    item = json.loads(sample.payload.to_string())
    try:
        q.put_nowait(item)
    except queue.Full:
        try:
            q.get_nowait()
        except queue.Empty:
            pass
        q.put_nowait(item)
