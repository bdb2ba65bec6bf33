"""A Zenoh client of the `tecdar/1` API: commands, event and state streams (used by the demo, CLI and tests)."""
from __future__ import annotations

import json
import logging
import queue
import threading
import time

import zenoh

from tecdard.api.session import DAEMON_NAME, Keys, TlsFiles, client_config, dumps

log = logging.getLogger("tecdar.client")

WAIT_REPORT_S = 10.0           # wait_alive says what it waits for this often
# Until the daemon listens, a liveliness query returns at once (no route): without a pause a wait
# spun a core at ~70 000 queries a second while the daemon started on the other one.
ALIVE_POLL_S = 0.05
FIRST_CONNECT_S = 0.25         # a new client tries this long to reach the daemon at once (then on first use)


class ClientError(RuntimeError):
    pass


class Denied(ClientError):
    """The daemon is alive, yet the command reached no queryable: a router's access control (the fleet's roster)
    does not let this session send it."""


DENIED_BEFORE = 0.5        # a query that ends with no reply within this share of its timeout was routed nowhere


class Client:
    """The daemon's client: a Zenoh session in client mode to the daemon's endpoint and nothing else
    (no gossip, no scouting), which takes what it receives on the robot's keys only from that node,
    and with mutual TLS only if that node's certificate is named `daemon_name`
    (tecdard.api.session.client_config). The session opens when the daemon is first reached
    (`alive`, `wait_alive`, `command`), and reconnects by itself after that."""

    def __init__(self, endpoint: str, robot: str = "sim", tls: TlsFiles | None = None,
                 open_timeout_s: float | None = None, daemon_name: str = DAEMON_NAME):
        """`tls`: this client's certificate and key and the CA, for a daemon on a tls/ endpoint;
        `daemon_name`: the common name of the daemon's certificate (or of the router's, through
        one). `open_timeout_s`: how long a transport's handshake may take (Zenoh's default, 10 s,
        is also how long closing the session waits on an endpoint that accepts TCP but never answers)."""
        self.endpoint, self.robot, self.tls = endpoint, robot, tls
        self.daemon_name, self.open_timeout_s = daemon_name, open_timeout_s
        self.keys = Keys(robot)
        self.session = None
        self._lock = threading.Lock()
        self.events: queue.Queue = queue.Queue()
        self.event_log: list[dict] = []       # every event seen, in order (wait_event consumes the queue)
        self.states: queue.Queue = queue.Queue(maxsize=1000)
        self.contacts: queue.Queue = queue.Queue(maxsize=10000)
        self._subs: list = []
        client_config(endpoint, robot, tls, daemon_name)       # a malformed endpoint or file: zenoh.ZError now
        self.connect(FIRST_CONNECT_S)

    def connect(self, timeout: float = 1.0) -> bool:
        """Open the session if it is not open yet: True once connected to the endpoint."""
        with self._lock:
            if self.session is not None:
                return True
            try:
                session = zenoh.open(client_config(self.endpoint, self.robot, self.tls, self.daemon_name,
                                                   self.open_timeout_s, connect_timeout_s=timeout))
            except zenoh.ZError as exc:
                if str(exc).startswith("Unable to connect"):
                    return False                  # nothing there yet: the daemon may be starting
                raise ClientError(f"cannot open a session to {self.endpoint}: {str(exc).splitlines()[0]}") from None
            self._subs = [
                session.declare_subscriber(self.keys.events, direct_callback(self._on_event)),
                session.declare_subscriber(self.keys.state, direct_callback(lambda s: _put_latest(self.states, s))),
                session.declare_subscriber(self.keys.contact, direct_callback(lambda s: _put_latest(self.contacts, s))),
            ]
            self.session = session
            return True

    def _on_event(self, sample) -> None:
        ev = json.loads(sample.payload.to_string())
        self.event_log.append(ev)
        self.events.put(ev)

    def close(self) -> None:
        with self._lock:
            if self.session is None:
                return
            for sub in self._subs:
                sub.undeclare()
            self.session.close()
            self.session = None

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def alive(self, timeout: float = 1.0) -> bool:
        t0 = time.monotonic()
        if not self.connect(timeout):
            return False
        timeout = max(timeout - (time.monotonic() - t0), 0.05)
        replies = self.session.liveliness().get(self.keys.alive, timeout=timeout)
        return any(r.ok is not None for r in replies)

    def robots_alive(self, timeout: float = 1.0) -> list[str]:
        """The robot names whose daemons hold a liveliness token at this endpoint (with the client
        opened for robot "*")."""
        if not self.connect(timeout):
            return []
        names = set()
        for r in self.session.liveliness().get(self.keys.alive, timeout=timeout):
            if r.ok is not None:
                parts = str(r.ok.key_expr).split("/")
                if len(parts) == 3:
                    names.add(parts[1])
        return sorted(names)

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
        if not self.connect(min(timeout, 2.0)):
            raise ClientError(f"{verb}: nothing answers at {self.endpoint}")
        kwargs = {"timeout": timeout}
        if payload is not None:
            kwargs["payload"] = payload
        t0 = time.monotonic()
        for reply in self.session.get(self.keys.cmd(verb), **kwargs):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_string())
            raise ClientError(f"{verb}: error reply {reply.err.payload.to_string()}")
        # no reply: a query that ended long before its timeout was routed to no queryable. With the daemon's
        # token in sight that is a router's access control, not a missing daemon (a watch-only operator's
        # rotate read "no reply within 5 s" after 0.8 s, and exit 3)
        if time.monotonic() - t0 < DENIED_BEFORE * timeout and self.alive(1.0):
            raise Denied(f"{verb}: denied: {self.keys.alive} is alive, but {self.keys.cmd(verb)} reached no "
                         "queryable: the router's access control does not let this certificate send it (the "
                         "fleet's roster: an operator's robots)")
        raise ClientError(f"{verb}: no reply within {timeout:.0f} s")

    def wait_event(self, kinds: tuple[str, ...], task: str | None = None, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        self.connect(min(timeout, FIRST_CONNECT_S))
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


def direct_callback(fn) -> zenoh.handlers.Callback:
    """`fn` run on Zenoh's own thread as the sample arrives. A plain callable would get a Python thread
    of its own (zenoh-python's `indirect` default), which is not a daemon thread: one whose session
    did not end it kept a test run's interpreter from exiting after its last test (CI, 2026-12-04).
    Each of these only parses and enqueues, never calls back into Zenoh, so it may run there."""
    def guarded(sample) -> None:
        try:
            fn(sample)
        except Exception as exc:           # a payload that is not our JSON: dropped, never Zenoh's thread
            log.debug("a message on %s was dropped: %s", sample.key_expr, exc)

    return zenoh.handlers.Callback(guarded, indirect=False)


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
