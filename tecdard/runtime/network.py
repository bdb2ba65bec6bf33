"""The daemon's `zenoh` section: its mode and endpoints, mutual TLS and who may command, read and checked
at start-up; and its session's network threads kept below the daemon's own."""
from __future__ import annotations

import os
from dataclasses import dataclass

from tecdard.api.session import (DAEMON_MAX_MESSAGE_BYTES, DAEMON_NAME, DEFAULT_ENDPOINT, Keys, TlsFiles,
                                 access_control, cert_common_name, endpoint_problem, session_config)
from tecdard.options import option, read_options
from tecdard.runtime.intake import IntakeParams
from tecdard.safejson import first_line, show

MAX_ENDPOINT_CHARS = 256
ROUTER_CHECK_S = 0.25          # a client-mode daemon looks this often whether a router still connects it
ZENOH_THREAD_NICE = 5          # Zenoh's network threads run this much nicer than the daemon's own


@dataclass(frozen=True)
class ZenohOptions:
    """The `zenoh` section's own options (its rates are IntakeParams', its security SecurityOptions')."""
    mode: str = option("peer", "peer: listens for clients itself (and may connect to a router too); client: "
                               "reaches everything through the routers in connect", choices=("peer", "client"))
    listen: list = option([DEFAULT_ENDPOINT], "endpoints it listens on (not 7447: zenohd's and rmw_zenohd's router "
                                              "port); `--listen` overrides", kind="custom",
                          shown=f'["{DEFAULT_ENDPOINT}"] (peer), [] (client)')
    connect: list = option([], "routers it connects to, e.g. [\"tcp/127.0.0.1:7447\"] (the host's rmw_zenohd)",
                           kind="strs", max_len=MAX_ENDPOINT_CHARS, max_items=16)
    multicast_scouting: bool = option(False, "scout for peers by multicast (off: it reaches only the endpoints "
                                             "named)")


@dataclass(frozen=True)
class SecurityOptions:
    """Who may command: the `zenoh` section's (a router's too), beside zenoh.tls (TlsOptions)."""
    commanders: list = option([], "certificate common names that may send commands (with zenoh.tls); others only "
                                  "watch; left out: every authenticated peer", kind="strs", max_len=256,
                              max_items=64)


@dataclass(frozen=True)
class TlsOptions:
    """The `zenoh.tls` section: mutual TLS (docs/zenoh-api.md); with it every endpoint must be tls/."""
    ca: str = option("", "every peer's certificate must be signed by this CA (PEM)", required=True, max_len=4096)
    cert: str = option("", "this side's certificate (PEM)", required=True, max_len=4096)
    key: str = option("", "its private key (PEM)", required=True, max_len=4096)


@dataclass(frozen=True)
class ZenohSettings:
    """Peer (default: listens for clients itself, and may also connect to a router on the host) or
    client (reaches everything through the routers in `connect`, listens on nothing)."""
    mode: str
    listen: list
    connect: list
    multicast: bool
    tls: TlsFiles | None
    commanders: list
    intake: IntakeParams

    @classmethod
    def from_config(cls, section, listen: list[str] | None = None) -> "ZenohSettings":
        """The `zenoh` section; `listen` (the command line's --listen) overrides zenoh.listen."""
        o = read_options(ZenohOptions, section)
        mode, connect, multicast = o.mode, o.connect, o.multicast_scouting
        configured = section.getstrlist("listen", [DEFAULT_ENDPOINT] if mode == "peer" else [],
                                        max_len=MAX_ENDPOINT_CHARS, max_items=16)
        listen = listen if listen is not None else configured
        if mode == "client" and listen:
            raise section.error("listen", "a Zenoh client listens on nothing; leave it out with mode: client")
        if mode == "client" and not connect:
            raise section.error("connect", "mode client needs a router's endpoint to connect to")
        if not listen and not connect:
            raise section.error("listen", "empty, and nothing in zenoh.connect: no client could reach the daemon")
        for key, endpoints in (("listen", listen), ("connect", connect)):
            for ep in endpoints:
                problem = endpoint_problem(ep)
                if problem:
                    raise section.error(key, f"{show(ep)}: {problem}")
        tls, commanders = _security(section, listen + connect)
        return cls(mode, list(listen), connect, multicast, tls, commanders, IntakeParams.from_config(section))

    def fleet_problem(self, robot: str) -> str | None:
        """Why a fleet's routers would refuse this daemon (docs/fleet.md): a client of a router on TLS whose
        certificate does not name its robot may publish and answer on none of its keys. None otherwise."""
        if self.mode != "client" or self.tls is None:
            return None
        name = cert_common_name(self.tls.cert)
        if name == robot:
            return None
        return (f"zenoh.tls.cert is named {name!r}, not robot.name {robot!r}: a fleet's routers (tecdard fleet acl) "
                "let a daemon publish and answer only under its certificate's robot")

    def session_config(self, keys: Keys, ros2: dict | None = None):
        """The daemon's Zenoh session config (zenoh.ZError where Zenoh refuses an endpoint); `ros2`: the
        ROS 2 node's key expressions, let through its access control."""
        acl = access_control(keys, self.commanders, ros2)
        conf = session_config(self.listen, self.connect, self.multicast, DAEMON_MAX_MESSAGE_BYTES, tls=self.tls,
                              acl=acl, mode=self.mode)
        if ros2 is not None:
            # the node's transient-local publishers (its actions' status) keep their cache by timestamp, as
            # rmw_zenoh's sessions do
            conf.insert_json5("timestamping/enabled", "true")
        return conf

    def where(self) -> str:
        parts = [f"listening on {', '.join(self.listen)}"] if self.listen else []
        if self.connect:
            parts.append(f"connecting to {', '.join(self.connect)}")
        if self.tls is not None:
            # what clients must expect (tecdard.api.session.client_access_control); through a router
            # they expect the router's name instead
            name = cert_common_name(self.tls.cert)
            parts.append(f"TLS as {name!r}" + ("" if name == DAEMON_NAME or self.mode == "client" else
                                                 f" (clients expect {DAEMON_NAME!r} unless told --tls-daemon-name)"))
        return f"Zenoh {self.mode}, " + " and ".join(parts)


def _security(section, endpoints: list[str]) -> tuple[TlsFiles | None, list[str]]:
    """zenoh.tls (mutual TLS: ca, cert, key) and zenoh.commanders (certificate common names that may
    send commands), checked: the files readable, every endpoint tls/ when TLS is on (a tcp/ beside it
    would let anyone in unauthenticated), and commanders only with TLS (names come from certificates)."""
    tls = None
    if section.has("tls"):
        sec = section.section("tls")
        tls_options = read_options(TlsOptions, sec)
        files = {}
        for key in ("ca", "cert", "key"):
            path = getattr(tls_options, key)
            try:
                with open(path, "rb") as fh:
                    if b"-----BEGIN" not in fh.read(64 * 1024):
                        raise sec.error(key, f"{show(path)} is not a PEM file")
            except OSError as exc:
                raise sec.error(key, f"cannot read {show(path)} ({exc.strerror})") from None
            files[key] = path
        tls = TlsFiles(**files)
        plain = [ep for ep in endpoints if not ep.startswith("tls/")]
        if plain:
            raise section.error("listen/connect", f"{show(plain[0])} is not a tls/ endpoint; with zenoh.tls every "
                                                  "endpoint must be, or unauthenticated peers get in beside it")
    elif any(ep.startswith("tls/") for ep in endpoints):
        raise section.error("tls", "a tls/ endpoint needs zenoh.tls (ca, cert, key)")
    commanders = read_options(SecurityOptions, section).commanders
    if commanders and tls is None:
        raise section.error("commanders", "needs zenoh.tls (the names are certificates' common names)")
    if section.has("commanders") and not commanders:
        raise section.error("commanders", "an empty list would let nobody command; leave it out to let every "
                                          "authenticated peer command")
    return tls, commanders


def renice_zenoh_threads() -> None:
    """Zenoh's network threads (rx-*, tx-*, net-*, acc-*, app-*: Rust, outside the GIL) at a lower
    CPU priority than the daemon's own threads. Under contention (a flood of queries decoded on
    them, a loaded host) the control loop, the IMU path and the estimator are served first; a
    process may always lower its own threads' priority. Best effort: Linux only, failures ignored."""
    from tecdard.runtime.realtime import threads_named
    for tid in threads_named(lambda name: name.split("-")[0] in ("rx", "tx", "net", "acc", "app")):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, 0) + ZENOH_THREAD_NICE)
        except OSError:
            pass


class RouterLink:
    """A client-mode daemon's link to its routers (zenoh.connect), looked at every ROUTER_CHECK_S on the
    main thread: `problem(now)` is why no router connects the daemon (then no command reaches it,
    `stop` included), or None. The session reconnects by itself (connect/retry); the control thread
    turns the problem into a robot_link fault while it holds."""

    def __init__(self, session, endpoints: list[str]):
        self.session, self.endpoints = session, endpoints
        self._next = 0.0
        self._problem: str | None = None

    def problem(self, now: float) -> str | None:
        if now >= self._next:
            self._next = now + ROUTER_CHECK_S
            connected = bool(self.session.info.routers_zid())
            self._problem = None if connected else (
                f"the Zenoh router ({', '.join(self.endpoints)}) cannot be reached: no command, stop "
                "included, can reach the daemon until it is back")
        return self._problem


def listen_error(exc: Exception, listen: list[str]) -> str:
    """Zenoh's refusal to listen as one line: a taken port names what to do."""
    text = str(exc)
    if "Address already in use" in text:
        taken = next((ep for ep in listen if ep in text), listen[0] if listen else "?")
        port = taken.rpartition(":")[2]
        return (f"{taken}: port {port} is taken: another tecdard? `tecdard status --connect {taken}` "
                "(or set zenoh.listen / --listen to a free port)")
    return f"Zenoh: {first_line(exc)}"
