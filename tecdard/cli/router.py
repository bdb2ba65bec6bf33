"""`tecdard router --config router.yaml`: the fleet's Zenoh router (tecdard.runtime.router), from its config."""
from __future__ import annotations

import sys


def main(args) -> int:
    """Run the router; exit 2 with one line on a bad config, 1 when it cannot listen."""
    from tecdard.config import Config, ConfigError
    from tecdard.runtime.router import RouterSettings, serve
    try:
        settings = RouterSettings(Config.load(args.config))
        conf = settings.session_config()
    except ConfigError as exc:
        print(f"tecdard router: config error: {exc}", file=sys.stderr)
        return 2
    return serve(settings, conf)


def add_parser(sub) -> None:
    p = sub.add_parser("router", help="run a Zenoh router (eclipse-zenoh's router mode) for a fleet's daemons and "
                                      "clients, where there is no zenohd",
                       description="A Zenoh router: zenoh.listen/connect/tls as the daemon's, access_control from "
                                   "the fleet's roster (roster: FILE) or an ACL document (file: FILE). docs/fleet.md")
    p.add_argument("--config", required=True, help="the router's YAML config (configs/router.yaml)")
    p.set_defaults(func=main)
