"""The `tecdard` command line: `run` the daemon, `demo` the whole pipeline on the simulated robot."""
from __future__ import annotations

import argparse
import logging
import sys

from tecdard.config import Config, ConfigError


def _cmd_run(args) -> int:
    try:
        cfg = Config.load(args.config)
        from tecdard.daemon import Daemon   # heavy imports only once the config file exists
        daemon = Daemon(cfg, listen=[args.listen] if args.listen else None)
    except ConfigError as exc:
        print(f"tecdard: config error: {exc}", file=sys.stderr)
        return 2
    return daemon.run()


def _cmd_demo(args) -> int:
    from tecdard.demo import run_demo
    return run_demo(args.config, args.angle)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tecdard", description="Transient extrinsic contact detection and ranging daemon")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run the daemon")
    p.add_argument("--config", required=True, help="YAML configuration file")
    p.add_argument("--listen", help="Zenoh endpoint to listen on, overrides zenoh.listen (e.g. tcp/127.0.0.1:7447)")
    p.set_defaults(func=_cmd_run)
    p = sub.add_parser("demo", help="start the daemon on the simulated robot and rotate the paper cutter")
    p.add_argument("--config", default="configs/sim.yaml")
    p.add_argument("--angle", type=float, default=30.0, help="rotation, degrees")
    p.set_defaults(func=_cmd_demo)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    return args.func(args)
