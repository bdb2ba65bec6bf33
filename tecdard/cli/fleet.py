"""The `tecdard fleet` subcommands: `acl` (the routers' access control from a roster), `status` and `watch`
(every robot that answers through a router)."""
from __future__ import annotations

import argparse
import os
import sys

EXIT_OK, EXIT_BAD_INPUT = 0, 2


def _acl(args) -> int:
    from tecdard.config import ConfigError
    from tecdard.fleet.acl import acl_document
    from tecdard.fleet.roster import Roster
    try:
        roster = Roster.load(args.roster)
    except ConfigError as exc:
        print(f"tecdard fleet acl: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = acl_document(roster, args.roster)
    if args.output in (None, "-"):
        sys.stdout.write(text)
    else:
        tmp = f"{args.output}.tmp"
        with open(tmp, "w") as fh:
            fh.write(text)
        os.replace(tmp, args.output)
        print(f"tecdard fleet acl: {len(roster.robots)} robots, {len(roster.operators)} operators, "
              f"{len(roster.routers)} routers -> {args.output}", file=sys.stderr)
    return EXIT_OK


def _finite_positive(text: str) -> float:
    value = float(text)
    if not 0.0 < value < 3600.0:
        raise argparse.ArgumentTypeError(f"{text}: expected seconds in (0, 3600)")
    return value


def add_parser(sub) -> None:
    from tecdard.cli.task_verbs import add_tls_options, default_connect
    from tecdard.cli.fleet_status import GATHER_S, run_status
    fleet = sub.add_parser("fleet", help="many arms: the routers' ACL from a roster, and every robot's status",
                           description="A fleet of daemons behind Zenoh routers (docs/fleet.md).")
    verbs = fleet.add_subparsers(dest="fleet_cmd", required=True)
    p = verbs.add_parser("acl", help="the routers' access_control section (JSON5) made from a roster file",
                         description="Print (or write) the access control every router of the fleet runs: for "
                                     "zenohd's config, and for `tecdard router` (access_control.file). Default deny.")
    p.add_argument("roster", help="the roster: robots, operators (name: [robots it may command]), routers (YAML)")
    p.add_argument("-o", "--output", help="write it here (atomically) instead of printing it")
    p.set_defaults(func=_acl)
    for name, watch in (("status", False), ("watch", True)):
        p = verbs.add_parser(name, help=("one table of every robot that answers through the router" if not watch else
                                         "the same table, redrawn until Ctrl-C"),
                             description="Columns: robot, mode, task, faults, last contact (x, y, z in mm, world), "
                                         "IMU rate (Hz), the control tick's overruns, link (ok, silent: alive but no "
                                         "state for 1 s, gone: no liveliness token, or the fault that cuts it).")
        p.add_argument("--connect", default=default_connect(), help="the router's endpoint (default %(default)s)")
        p.add_argument("--robot", default="*", help="robots to show: a name or a Zenoh chunk pattern (default *)")
        p.add_argument("--json", action="store_true", help="the rows as JSON (SI units: contact_p in m)")
        add_tls_options(p, "the router's", "operator's certificate")
        if watch:
            p.add_argument("--period", type=_finite_positive, default=1.0, help="seconds between tables (default 1)")
        else:
            p.add_argument("--wait", type=_finite_positive, default=GATHER_S,
                           help="seconds to wait for the robots' states at most (default %(default)g)")
        p.set_defaults(func=lambda args, watch=watch: run_status(args, watch))
