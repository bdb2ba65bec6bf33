"""The fleet's Zenoh router (`tecdard router --config router.yaml`, tecdard.cli.router): a Zenoh router of eclipse-zenoh's own (router mode, not a relay of
ours) for hosts without zenohd: its endpoints, mutual TLS and access control from the config, the ACL made
from the fleet's roster (fleet.acl) or read from a file as `tecdard fleet acl` writes it."""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading

from tecdard.config import Config, ConfigError
from tecdard.safejson import first_line, show

log = logging.getLogger("tecdar")

ROUTER_PORT_HINT = "tls/0.0.0.0:7447"          # zenohd's own port: a host runs one router
MAX_ACL_FILE_BYTES = 4 << 20


class RouterSettings:
    """The router's config: `zenoh` (listen, connect, tls as the daemon's) and `access_control`
    (roster: a roster file, or file: an ACL document; left out: no access control, said at start)."""

    def __init__(self, cfg: Config):
        from tecdard.api.session import endpoint_problem
        from tecdard.runtime.network import MAX_ENDPOINT_CHARS, _security
        z = cfg.section("zenoh")
        self.listen = z.getstrlist("listen", max_len=MAX_ENDPOINT_CHARS, max_items=16)
        self.connect = z.getstrlist("connect", [], max_len=MAX_ENDPOINT_CHARS, max_items=64)
        if not self.listen:
            raise z.error("listen", f"empty: a router listens for its daemons and clients (e.g. {ROUTER_PORT_HINT})")
        for key, endpoints in (("listen", self.listen), ("connect", self.connect)):
            for ep in endpoints:
                problem = endpoint_problem(ep)
                if problem:
                    raise z.error(key, f"{show(ep)}: {problem}")
        self.tls, commanders = _security(z, self.listen + self.connect)
        if commanders:
            raise z.error("commanders", "a daemon's option: a router's access control is access_control "
                                        "(roster: or file:)")
        self.acl, self.acl_source = None, "none"
        if cfg.has("access_control"):
            a = cfg.section("access_control")
            roster, path = a.getstr("roster", "", max_len=4096), a.getstr("file", "", max_len=4096)
            if bool(roster) == bool(path):
                raise a.error("roster/file", "give one: roster (the ACL made from it) or file (an ACL document)")
            if roster:
                from tecdard.fleet.acl import router_access_control
                from tecdard.fleet.roster import Roster
                self.acl, self.acl_source = router_access_control(Roster.load(roster)), f"roster {roster}"
            else:
                self.acl, self.acl_source = read_acl_file(path), f"file {path}"
        cfg.check_unused()

    def session_config(self):
        from tecdard.api.session import session_config
        return session_config(self.listen, self.connect, tls=self.tls, acl=self.acl, mode="router")


def read_acl_file(path: str) -> dict:
    """The access_control section of a JSON5 document (as `tecdard fleet acl` writes it, or a zenohd
    config holding one), checked by Zenoh's own parser; ConfigError naming the file otherwise."""
    import zenoh
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_ACL_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"access_control.file: cannot read {show(path)} ({exc.strerror})") from None
    if len(raw) > MAX_ACL_FILE_BYTES:
        raise ConfigError(f"access_control.file: {show(path)} is over {MAX_ACL_FILE_BYTES >> 20} MiB")
    try:
        conf = zenoh.Config.from_json5(raw.decode("utf-8"))
        import json
        acl = json.loads(conf.get_json("access_control"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"access_control.file: {show(path)}: {_first_line(exc)}") from None
    except Exception as exc:          # zenoh.ZError: not JSON5, or not a valid Zenoh config
        raise ConfigError(f"access_control.file: {show(path)}: {_first_line(exc)}") from None
    if not isinstance(acl, dict) or not acl.get("enabled"):
        raise ConfigError(f"access_control.file: {show(path)} holds no enabled access_control section")
    return acl


def _first_line(exc: BaseException) -> str:
    """Zenoh's parse error (` --> line:column`, the text, `= expected ...`) or any other, as one line."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    if lines and lines[0].startswith("-->"):
        where = lines[0].removeprefix("-->").strip().split(":")
        said = next((line.lstrip("= ") for line in lines if line.startswith("=")), "not JSON5")
        return f"line {where[0]} column {where[-1]}: {said}"[:200]
    return first_line(exc, 200)


# Zenoh's own log in the router's (RUST_LOG overrides): its warnings, among them each refused TLS handshake (a
# client without TLS, another CA's certificate), and access control's word on each certificate that matches no
# subject of the roster. A denied message of a known subject is logged at zenoh's trace level only, with every
# message passed (`RUST_LOG=warn,zenoh::net::routing::interceptor::access_control=trace`: for a session's debugging).
ROUTER_LOG = "warn,zenoh::net::routing::interceptor::access_control=info"


def serve(settings: RouterSettings, conf) -> int:
    """Run the router on its session config `conf` (settings.session_config()) until SIGTERM or Ctrl-C;
    READY=1 to systemd once it listens."""
    import zenoh
    from tecdard.runtime.network import listen_error
    from tecdard.runtime.sdnotify import Notifier
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    os.environ.setdefault("NO_COLOR", "1")          # plain text for journald (tracing-subscriber reads it)
    zenoh.init_log_from_env_or(ROUTER_LOG)
    try:
        session = zenoh.open(conf)
    except Exception as exc:          # zenoh.ZError: an endpoint taken, a certificate refused
        print(f"tecdard router: {listen_error(exc, settings.listen)}", file=sys.stderr)
        return 1
    with session:
        tls = "mutual TLS" if settings.tls is not None else "no TLS (anyone who reaches it gets in)"
        print(f"tecdard router: Zenoh router {session.zid()} listening on {', '.join(settings.listen)}"
              + (f", connecting to {', '.join(settings.connect)}" if settings.connect else "")
              + f"; {tls}; access control: {settings.acl_source}", file=sys.stderr, flush=True)
        notifier = Notifier()
        notifier.notify("READY=1")
        while not stop.wait(1.0):
            pass
        notifier.notify("STOPPING=1")
    return 0
