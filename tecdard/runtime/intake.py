"""Zenoh queries in, commands out: `stop` ahead of everything, every other query bounded in cost and rate.

The queryables under `tecdar/{robot}/cmd/`:
- `cmd/stop` has a callback of its own (Zenoh's callback thread): it registers the query and hands
  a `Stop` to the control thread at once, so a stop never waits behind other queries.
- each task verb, `cancel`, `grasp` and `release` (the "task" class), `cmd/record` ("record": a capture costs a file,
  so a flood of it must not spend the task verbs' budget), `cmd/status` ("status"), and `cmd/**`
  for every other key ("other": unknown verbs such as `cmd/stop/now`, which get `unknown_verb`)
  fill Zenoh ring channels of their own that the main thread polls. A flood overwrites the oldest queued
  queries of its own class in Zenoh's memory (their senders get no reply) without costing Python
  anything, and a flood of `status` never pushes a `rotate` out of its ring. (`cmd/**` also sees a
  copy of every query to a known verb; it drops those unanswered.)

The main thread then spends a bounded amount of work on each query it takes: the payload's size
is checked before a byte is decoded, parsing is bounded (tecdard.safejson), and a token bucket per
class limits how many queries per second are parsed at all (a large payload costs more). Queries
over the limit get a `rate_limited` reply while a refusal budget lasts, and are dropped beyond it,
so that a flood can never buy more than a fixed share of the main thread. A flood of one task
verb's key can still crowd out that verb for other clients: restricting who may send commands at
all is Zenoh's access control (docs/zenoh-api.md, "Who may command the robot").
"""
from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from dataclasses import dataclass

import zenoh

from tecdard.api import commands as C
from tecdard.options import option, read_options
from tecdard.runtime.messages import Cancel, Grip, Recover, Reply, StartTask, Stop
from tecdard.safejson import show_name
from tecdard.api.session import JSON, Keys, dumps

log = logging.getLogger("tecdar.intake")

BACKLOG = {"task": 8, "record": 4, "status": 64, "other": 16}   # queries waiting per ring (the oldest overwritten)
QUERIES_PER_POLL = 16          # per ring and pass; then the main thread serves replies and telemetry
MAX_PENDING_STOPS = 64         # stop queries waiting for the arm to come to rest; more are dropped (the stop holds)
REFUSALS_PER_S = 100.0         # budget of rate_limited replies; beyond it a query is left to its ring
REFUSAL_BURST = 50
PAYLOAD_COST_BYTES = 1024      # a query costs one token plus one per this many payload bytes
MIN_BURST = 5.0                # a class's burst: a second's worth of its rate, and never fewer queries than this
LOG_REFUSALS_PER_S = 5         # refusals logged one by one per second; the rest are counted


@dataclass
class IntakeParams:
    """Queries parsed per second, sustained and in a burst, per class (a large payload counts more)."""
    max_task_rate_hz: float = option(20.0, "task commands parsed per second (+1 per KiB of payload); more get "
                                           "rate_limited", unit="Hz", minval=1.0, maxval=10000.0)
    max_status_rate_hz: float = option(100.0, "status queries parsed per second", unit="Hz", minval=1.0,
                                       maxval=10000.0)
    max_other_rate_hz: float = option(20.0, "other keys under cmd/ (unknown verbs) parsed per second", unit="Hz",
                                      minval=1.0, maxval=10000.0)
    max_record_rate_hz: float = option(10.0, "record queries parsed per second (each may write a file)", unit="Hz",
                                       minval=1.0, maxval=10000.0)

    @classmethod
    def from_config(cls, section) -> "IntakeParams":
        return read_options(cls, section)

    def rate(self, klass: str) -> float:
        return {"task": self.max_task_rate_hz, "status": self.max_status_rate_hz,
                "record": self.max_record_rate_hz}.get(klass, self.max_other_rate_hz)


class TokenBucket:
    """`rate` tokens per second, at most `burst` saved up."""

    def __init__(self, rate: float, burst: float, now: float | None = None):
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.t = time.monotonic() if now is None else now

    def ready(self, now: float, cost: float = 1.0) -> bool:
        """Whether `cost` tokens are there (refilled to now), without taking them."""
        self.tokens = min(self.burst, self.tokens + max(0.0, now - self.t) * self.rate)
        self.t = max(self.t, now)
        return self.tokens >= cost

    def take(self, now: float, cost: float = 1.0) -> bool:
        if self.ready(now, cost):
            self.tokens -= cost
            return True
        return False


class QueryIntake:
    """Owned by the main thread, except `on_stop`, which Zenoh calls on its callback thread.

    `control` is anything with `submit(msg) -> bool` (a StartTask or Cancel; False when its queue
    is full) and `request_stop(Stop)`; `status_json()` gives the latest state as JSON text.
    """

    def __init__(self, keys: Keys, limits: C.Limits, control, status_json, params: IntakeParams | None = None,
                 record=None, read_only: str | None = None):
        """`record(action, label) -> reply dict` answers `record` (CommandError to refuse). `read_only`:
        the daemon does not command this arm, and task verbs are refused with this message.

        A query is a zenoh.Query or anything with its `key_expr`, `payload` and `reply(key, text,
        encoding)`: the ROS 2 node's service calls come through here as their Zenoh verbs."""
        self.read_only = read_only
        self.keys = keys
        self.record = record
        self.limits = limits
        self.control = control
        self.status_json = status_json
        self._limits_json = dumps(dataclasses.asdict(limits))    # status tells clients the limits (the CLI's --help)
        self.params = params or IntakeParams()
        self._stop_key = keys.cmd("stop")
        self._pending: dict[int, zenoh.Query] = {}
        self._pending_stops = 0
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._task_keys = {keys.cmd(v) for v in C.task_verbs() + ("cancel", "recover") + C.GRIP_VERBS}
        self._record_key = keys.cmd("record")
        self._known_keys = {keys.cmd(v) for v in C.verbs()}
        self._parse = {k: TokenBucket(self.params.rate(k), max(self.params.rate(k), MIN_BURST)) for k in BACKLOG}
        self._refuse = TokenBucket(REFUSALS_PER_S, REFUSAL_BURST)
        self._log_second, self._logged, self._unlogged = 0, 0, 0
        self._rings: list[tuple[str, object]] = []        # (class, queryable), polled in this order
        self._declared: list = []
        self.counters = {"queries": 0, "stops": 0, "refused": 0, "rate_limited": 0, "dropped": 0}

    def declare(self, session: zenoh.Session) -> None:
        self._declared.append(session.declare_queryable(self._stop_key, self.on_stop))
        rings = [("task", key) for key in sorted(self._task_keys)]
        rings += [("record", self._record_key), ("status", self.keys.cmd("status")), ("other", self.keys.cmd_all)]
        for klass, key in rings:
            ring = session.declare_queryable(key, zenoh.handlers.RingChannel(BACKLOG[klass]))
            self._rings.append((klass, ring))
            self._declared.append(ring)

    def undeclare(self) -> None:
        for q in self._declared:
            try:
                q.undeclare()
            except Exception:
                log.debug("undeclaring a queryable failed", exc_info=True)
        self._declared.clear()
        self._rings.clear()

    # -- the stop path (Zenoh's callback thread) -----------------------------
    def on_stop(self, query) -> None:
        """Register the query and hand the control thread a Stop; nothing else, never blocking.
        Whatever its payload says, a stop stops (it never moves the arm)."""
        if str(query.key_expr) != self._stop_key:
            return          # a wildcard query such as cmd/*: its copy in the ring is refused there
        with self._lock:
            if self._pending_stops >= MAX_PENDING_STOPS:
                self.counters["dropped"] += 1
                return
            self._pending_stops += 1
            request = next(self._ids)
            self._pending[request] = query
            self.counters["stops"] += 1
        self.control.request_stop(Stop(request))

    # -- everything else (the main thread) -----------------------------------
    def poll(self, now: float | None = None) -> int:
        """Take up to QUERIES_PER_POLL queued queries of each ring; returns how many were taken.

        A ring whose class has spent its parsing budget, with the refusal budget spent too, is
        not looked at: its queries wait, and a flood overwrites them in Zenoh's memory, so the
        main thread's share of any flood is bounded by the budgets, not by the flood's rate."""
        now = time.monotonic() if now is None else now
        total = 0
        for klass, ring in self._rings:
            for _ in range(QUERIES_PER_POLL):
                # The "other" ring is always drained: it holds a copy of every query to a known verb
                # (cmd/** matches them all), and Zenoh's default consolidation (latest) holds back a
                # query's replies until every queryable that got it is done with it. A copy left in
                # the ring delayed stop's reply under a flood by 100-250 ms, after the daemon had sent it.
                if klass != "other" and not self._parse[klass].ready(now) and not self._refuse.ready(now):
                    break
                query = ring.try_recv()
                if query is None:
                    break
                total += 1
                key = str(query.key_expr)
                if klass != "other" or key not in self._known_keys:
                    self.handle(query, key, query.payload, now)
                del query       # dropping the Query sends Zenoh's final reply: the sender stops waiting
        return total

    def _class(self, key: str) -> str:
        if key in self._task_keys:
            return "task"
        if key == self._record_key:
            return "record"
        return "status" if key == self.keys.cmd("status") else "other"

    def charge(self, query, key: str, size: int, now: float) -> bool:
        """Charge a query of `size` payload bytes to its class's budget before anything of it is parsed:
        False when the budget refuses it (answered rate_limited while the refusals' own budget lasts, else
        dropped) or it is over the size limit (answered payload_too_large, unread). A front door that must
        decode before the intake parses (the ROS 2 node's CDR) calls this first, then `handle(charged=True)`."""
        klass = self._class(key)
        prefix = self.keys.cmd_prefix
        verb = key[len(prefix):] if key.startswith(prefix) else key
        # parsing costs by size; an oversized payload is refused unread, at the cost of an empty query
        # (the refusal costs nothing to send, so it is sent)
        cost = 1.0 + (size / PAYLOAD_COST_BYTES if size <= C.MAX_PAYLOAD_BYTES else 0.0)
        if not self._parse[klass].take(now, cost):
            if self._refuse.take(now):
                self.counters["rate_limited"] += 1
                self._send(query, C.CommandError(C.RATE_LIMITED, f"{show_name(verb)}: over "
                                                 f"{self.params.rate(klass):g} queries per second; "
                                                 "try again later").reply())
            else:
                self.counters["dropped"] += 1
            return False
        if size > C.MAX_PAYLOAD_BYTES:          # refused unread
            exc = C.CommandError(C.PAYLOAD_TOO_LARGE, f"payload: {size} bytes, at most {C.MAX_PAYLOAD_BYTES}")
            self.counters["refused"] += 1
            self._log_refusal(now, verb, exc)
            self._send(query, exc.reply())
            return False
        return True

    def handle(self, query, key: str, payload, now: float, charged: bool = False) -> None:
        """One query of key `key` with `payload` (zenoh.ZBytes, bytes or None): refused, answered, or
        handed to the control thread (`charged`: its budget was taken already, by `charge`). No input raises."""
        self.counters["queries"] += 1
        prefix = self.keys.cmd_prefix
        verb = key[len(prefix):] if key.startswith(prefix) else key
        if key == self._stop_key:
            return          # the stop queryable has it (a stop's copies elsewhere are not answered)
        size = len(payload) if payload is not None else 0
        if not charged and not self.charge(query, key, size, now):
            return
        try:
            raw = None if payload is None else (payload if isinstance(payload, (bytes, str)) else payload.to_bytes())
            fields = C.admit(verb, raw, self.limits)
            if verb == "status":
                self._send_text(query, '{"ok":true,"state":' + (self.status_json() or "null")
                                + ',"limits":' + self._limits_json + "}")
                return
            if verb == "record":
                if self.record is None:
                    raise C.CommandError(C.NOT_IMPLEMENTED, "record: this daemon does not record")
                self._send(query, self.record(fields["action"], fields["label"]))
                return
            if self.read_only and (verb in C.task_verbs() or verb in C.GRIP_VERBS or verb == "recover"):
                raise C.CommandError(C.READ_ONLY, f"{verb}: {self.read_only}")
            request = self._register(query)
            msg = Cancel(request, fields["task"]) if verb == "cancel" else Recover(request) if verb == "recover" \
                else Grip(request, verb, fields) if verb in C.GRIP_VERBS else StartTask(request, verb, fields)
            if not self.control.submit(msg):
                self._forget(request)
                raise C.CommandError(C.BUSY, f"{verb}: control queue full, try again")
        except C.CommandError as exc:
            self.counters["refused"] += 1
            self._log_refusal(now, verb, exc)
            self._send(query, exc.reply())
        except Exception as exc:            # a bug here must cost one reply, never the daemon
            log.exception("handling a query on %s failed", show_name(key))
            self._send(query, C.CommandError(C.BAD_REQUEST, f"{show_name(verb)}: the request could not be "
                                             f"handled ({type(exc).__name__}, logged)").reply())

    def deliver(self, reply: Reply) -> None:
        """The control thread's answer to a registered query."""
        query = self._forget(reply.request)
        if query is not None:
            self._send(query, reply.payload)

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    # -- helpers ---------------------------------------------------------------
    def _register(self, query) -> int:
        with self._lock:
            request = next(self._ids)
            self._pending[request] = query
            return request

    def _forget(self, request: int):
        with self._lock:
            query = self._pending.pop(request, None)
            if query is not None and str(query.key_expr) == self._stop_key:
                self._pending_stops -= 1
            return query

    def _send(self, query, payload: dict) -> None:
        self._send_text(query, dumps(payload))

    @staticmethod
    def _send_text(query, text: str) -> None:
        if query is None:
            return
        try:
            # the query's own key expression: it may be a wildcard (cmd/*), which Zenoh accepts as the
            # reply key, and a concrete verb's key is the natural one
            query.reply(query.key_expr, text, encoding=JSON)
        except Exception as exc:          # the sender may have gone; never let it kill the loop
            log.debug("reply to %s failed: %s", show_name(str(query.key_expr)), exc)

    def _log_refusal(self, now: float, verb: str, exc: C.CommandError) -> None:
        second = int(now)
        if second != self._log_second:
            if self._unlogged:
                log.info("%d more refusals in the last second not logged one by one", self._unlogged)
            self._log_second, self._logged, self._unlogged = second, 0, 0
        if self._logged < LOG_REFUSALS_PER_S:
            self._logged += 1
            log.info("refused %s: %s (%s)", show_name(verb), exc.message, exc.code)
        else:
            self._unlogged += 1

