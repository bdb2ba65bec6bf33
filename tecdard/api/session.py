"""Zenoh session configuration and the `tecdar/1` key expressions."""
from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass

import zenoh

from tecdard.safejson import json_ready, nonfinite_path

log = logging.getLogger("tecdar")

JSON = zenoh.Encoding.APPLICATION_JSON
# The daemon's transport drops any message larger than this before it reaches Python (Zenoh's own
# default is 1 GiB); commands are refused with a reply above tecdard.commands.MAX_PAYLOAD_BYTES.
# 2 MiB, so that a payload of a megabyte (either kind) is answered `payload_too_large`, not dropped;
# the queries waiting in the intake's rings (132 at most) then hold at most 264 MiB.
DAEMON_MAX_MESSAGE_BYTES = 2 << 20
# Where the daemon listens and clients connect by default: loopback, and not 7447, the port of zenohd
# and of ROS 2's rmw_zenohd, beside which a daemon there could not start.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7507"


IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
PATH_PROTOCOLS = ("unixsock-stream",)
_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)$")


def endpoint_refused(endpoint: str, timeout_s: float = 1.0) -> str | None:
    """Whether nothing listens at a tcp/ or tls/ endpoint (its TCP connection refused, at once), in one line;
    None when something answers, or when it cannot be told this way (another protocol, a host that does not
    answer at all: then the liveliness wait says so)."""
    import socket
    proto, _, address = endpoint.partition("/")
    if proto not in ("tcp", "tls") or endpoint_problem(endpoint):
        return None
    host, _, port = address.split("#")[0].split("?")[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return None
    except ConnectionRefusedError:
        return (f"nothing listens at {endpoint} (connection refused): is the daemon (or the router) running, "
                "and is this its zenoh.listen?")
    except OSError:
        return None


def speaks_tls(endpoint: str, timeout_s: float = 1.0) -> bool:
    """Whether a tcp/ endpoint answers a TLS ClientHello as a TLS server does (a handshake or an alert record):
    a `tcp/` endpoint given for a router that listens on TLS. Asked only once a plain session saw nothing."""
    import socket
    import ssl
    proto, _, address = endpoint.partition("/")
    if proto != "tcp" or endpoint_problem(endpoint):
        return False
    host, _, port = address.split("#")[0].split("?")[0].rpartition(":")
    ctx = ssl.create_default_context()
    ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    tls = ctx.wrap_bio(incoming, outgoing)
    try:
        tls.do_handshake()
    except ssl.SSLWantReadError:
        pass                                   # the ClientHello is in `outgoing`
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s) as sock:
            sock.sendall(outgoing.read())
            first = sock.recv(3)
    except OSError:
        return False
    # a TLS record: content type handshake (22) or alert (21), then version 3.x
    return len(first) >= 2 and first[0] in (21, 22) and first[1] == 3


def endpoint_problem(endpoint: str) -> str | None:
    """Why a Zenoh endpoint (`proto/host:port`, or `unixsock-stream/PATH`, with optional `?...`
    and `#...`) cannot work, in a few words; None when it looks usable."""
    if not isinstance(endpoint, str) or "/" not in endpoint:
        return "expected <protocol>/<address>, e.g. tcp/127.0.0.1:7508"
    proto, _, address = endpoint.partition("/")
    address = address.split("#")[0].split("?")[0]
    if proto in PATH_PROTOCOLS:
        return None if address else "expected a socket path"
    if proto not in IP_PROTOCOLS:
        return f"unknown protocol {proto[:20]!r} (known: {', '.join(IP_PROTOCOLS + PATH_PROTOCOLS)})"
    host, sep, port = address.rpartition(":")
    if not sep or not _HOST.match(host):
        return "expected host:port"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        return f"port {port[:10]!r} is not 0..65535"
    return None


@dataclass(frozen=True)
class TlsFiles:
    """Mutual TLS: this side's certificate and key, and the CA every peer's certificate must be signed by."""
    ca: str
    cert: str
    key: str


CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 1.5}


def session_config(listen: list[str], connect: list[str], multicast_scouting: bool = False,
                   max_message_bytes: int | None = None, tls: TlsFiles | None = None,
                   acl: dict | None = None, mode: str = "peer", open_timeout_s: float | None = None) -> zenoh.Config:
    """A Zenoh session's config; multicast scouting is off unless explicitly enabled.

    - `max_message_bytes` (the daemon): larger messages are dropped by the transport, and shared
      memory is off, so that no payload bypasses that limit (Zenoh moves large messages between
      processes of one host through shared memory, unfragmented).
    - `tls`: mutual TLS on every tls/ endpoint, listening and connecting: each side presents its
      certificate and checks the other's against the CA.
    - `acl`: Zenoh's access control section (tecdard.daemon builds it from zenoh.commanders).
    - `mode`: "peer" (the daemon and its clients), "client", or "router" (a local router).
    - `open_timeout_s`: the transport handshake's limit (Zenoh's default is 10 s).
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    # An endpoint not up yet (a client started beside its daemon, a daemon before its router) is
    # retried from 0.1 s, at most every 0.5 s: Zenoh's own default backs off from 1 s to 4 s, so a
    # client could see a daemon seconds after it was ready.
    conf.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    if max_message_bytes is not None:
        conf.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
        conf.insert_json5("transport/shared_memory/enabled", "false")
    if tls is not None:
        for key, value in (("root_ca_certificate", tls.ca), ("listen_certificate", tls.cert),
                           ("listen_private_key", tls.key), ("connect_certificate", tls.cert),
                           ("connect_private_key", tls.key), ("enable_mtls", True)):
            conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    if acl is not None:
        conf.insert_json5("access_control", json.dumps(acl))
    if open_timeout_s is not None:
        conf.insert_json5("transport/unicast/open_timeout", str(max(1, int(open_timeout_s * 1000))))
    return conf


def access_control(keys: "Keys", commanders: list[str] | None = None, ros2: dict | None = None) -> dict:
    """The daemon's Zenoh access control, on every session it opens (default deny):
    - anyone it lets in may subscribe to anything and ask for liveliness (it then gets what the
      daemon publishes: `state`, `contact`, `events` and the `alive` token);
    - with `ros2` (tecdard.runtime.ros2_node.acl_keys: the ROS 2 node's key expressions) also the node's
      topics, tokens and services, its services commanded as the `cmd/**` keys are, and the
      publications of the topic it subscribes to (joint states);
    - the daemon publishes, holds its token and answers only on its own keys;
    - queries on `cmd/**` come in from everyone, or with `commanders` (certificates' common
      names, with mutual TLS) only from those peers; a refused query reaches no queryable;
    - nothing else comes in: no other session's publication, token, queryable or reply, on any
      key. So no one connected to the daemon can answer for it or publish as it through it, as a
      Zenoh peer would otherwise route for its clients (a queryable on `**` included)."""
    watch = [keys.state, keys.contact, keys.events, keys.alive]
    ros2 = ros2 or {}
    watch += ros2.get("publish", []) + ros2.get("tokens", [])
    serve = [keys.cmd_all] + ros2.get("serve", [])
    subjects = [{"id": "everyone"}]
    if commanders:
        subjects.append({"id": "commanders", "cert_common_names": list(commanders)})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "watch", "permission": "allow", "flows": ["ingress"],
             "key_exprs": ["**"] + (["@ros2_lv/**"] if ros2 else []),
             "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]},
            {"id": "publish", "permission": "allow", "flows": ["egress"], "key_exprs": watch,
             "messages": ["put", "liveliness_token", "reply"]},
            {"id": "serve", "permission": "allow", "flows": ["egress"], "key_exprs": serve,
             "messages": ["declare_queryable", "reply"]},
            {"id": "command", "permission": "allow", "flows": ["ingress"], "key_exprs": serve,
             "messages": ["query"]},
        ] + ([{"id": "subscribe", "permission": "allow", "flows": ["egress"], "key_exprs": ros2["subscribe"],
               "messages": ["declare_subscriber"]},
              {"id": "observe", "permission": "allow", "flows": ["ingress"], "key_exprs": ros2["subscribe"],
               "messages": ["put"]}] if ros2.get("subscribe") else []),
        "subjects": subjects,
        "policies": [{"rules": ["watch", "publish"] + (["subscribe", "observe"] if ros2.get("subscribe") else []),
                      "subjects": ["everyone"]},
                     {"rules": ["serve", "command"], "subjects": ["commanders" if commanders else "everyone"]}],
    }


DAEMON_NAME = "tecdard"      # the daemon's certificate's common name that clients expect, unless told another


def cert_common_name(path: str) -> str | None:
    """The subject's common name of a PEM certificate, or None where it cannot be read."""
    import ssl
    try:
        subject = ssl._ssl._test_decode_cert(path)["subject"]       # the standard library's own decoder
    except Exception:
        return None
    return next((value for rdn in subject for key, value in rdn if key == "commonName"), None)


def client_access_control(keys: "Keys", daemon_name: str | None) -> dict:
    """A client's own access control (default deny): it takes publications, replies, liveliness
    tokens and queryables on the robot's keys only from the node it connects to, and with mutual
    TLS only if that node's certificate is named `daemon_name`. A process that takes the
    daemon's port, or any other node, then answers nothing and publishes nothing the client sees."""
    node = {"id": "daemon"} if daemon_name is None else {"id": "daemon", "cert_common_names": [daemon_name]}
    mine = [keys.base_all]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "from_daemon", "permission": "allow", "flows": ["ingress"], "key_exprs": mine,
             "messages": ["put", "reply", "liveliness_token", "declare_queryable"]},
            {"id": "to_daemon", "permission": "allow", "flows": ["egress"], "key_exprs": mine,
             "messages": ["query", "declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"]},
        ],
        "subjects": [node],
        "policies": [{"rules": ["from_daemon", "to_daemon"], "subjects": ["daemon"]}],
    }


def client_config(endpoint: str, robot: str, tls: TlsFiles | None = None, daemon_name: str = DAEMON_NAME,
                  open_timeout_s: float | None = None, connect_timeout_s: float = 1.0) -> zenoh.Config:
    """A client's session: Zenoh client mode to the one endpoint, and nothing else. A peer learns
    other peers' addresses by gossip and connects to them, where the daemon's access control does
    not apply (an impostor answered the daemon's queries that way); a client reaches only the
    node it names, which routes for it. With `tls` the node must hold a certificate named
    `daemon_name` (client_access_control). The session opens once connected, or raises
    zenoh.ZError after `connect_timeout_s`; once open it reconnects by itself."""
    conf = session_config([], [endpoint], tls=tls, mode="client", open_timeout_s=open_timeout_s,
                          acl=client_access_control(Keys(robot), daemon_name if tls is not None else None))
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/timeout_ms", json.dumps({"client": max(1, int(connect_timeout_s * 1000))}))
    return conf


class Keys:
    def __init__(self, robot: str):
        base = f"tecdar/{robot}"
        self.state = f"{base}/state"
        self.contact = f"{base}/contact"
        self.events = f"{base}/events"
        self.alive = f"{base}/alive"
        self.cmd_prefix = f"{base}/cmd/"
        self.cmd_all = f"{base}/cmd/**"     # every key under cmd/: unknown verbs get an unknown_verb reply
        self.base_all = f"{base}/**"

    def cmd(self, verb: str) -> str:
        return self.cmd_prefix + verb


def dumps(obj) -> str:
    """Compact JSON for the wire, with no NaN or Infinity in it ever (JSON has no such numbers):
    a non-finite number goes out as null, and where it was is logged once per place. A robot's
    non-finite reading never gets this far (robots.state_check refuses it as a fault); this is
    the last guard for whatever else computes one."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False)
    except ValueError:
        where = nonfinite_path(obj)
        if where not in _NONFINITE_SAID and len(_NONFINITE_SAID) < NONFINITE_PLACES_SAID:
            _NONFINITE_SAID.add(where)
            log.warning("a non-finite number at %s went out as null", where)
        return json.dumps(json_ready(obj), separators=(",", ":"), allow_nan=False)


NONFINITE_PLACES_SAID = 64        # places of non-finite numbers logged, each once
_NONFINITE_SAID: set = set()
