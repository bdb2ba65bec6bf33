"""The `tecdard` command line: `run` the daemon; the task verbs, `status`, `stop`, `cancel` and `record` as
its client; and the offline tools (tecdard/tools/), each of which adds its own subcommand."""
from __future__ import annotations

import argparse
import logging
import os
import re
import sys

from tecdard.config import Config, ConfigError


def _cmd_run(args) -> int:
    # maps, recordings and logs the daemon writes are the operator's alone (0600/0700), as the
    # unit's UMask=0077 has it, whoever starts the daemon
    os.umask(0o077)
    try:
        cfg = Config.load(args.config)
        from tecdard.tools.kernel_cache import announce_compile
        announce_compile()
        from tecdard.runtime.daemon import Daemon   # heavy imports only once the config file exists
        daemon = Daemon(cfg, listen=[args.listen] if args.listen else None)
    except ConfigError as exc:
        print(f"tecdard: config error: {exc}", file=sys.stderr)
        return 2
    from tecdard.robots.backends import BackendError
    try:
        return daemon.run()
    except BackendError as exc:
        print(f"tecdard: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:        # zenoh.ZError: cannot listen (address in use, no such interface)
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        print(f"tecdard: Zenoh: {str(exc).splitlines()[0][:300]}", file=sys.stderr)
        return 1


_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d)")


def join_negative_values(argv: list[str]) -> list[str]:
    """`--direction -0.26,0,0.96` as `--direction=-0.26,0,0.96`: argparse takes a value that starts
    with '-' and is not one plain number for an option, and the vector arguments are lists."""
    out: list[str] = []
    for arg in argv:
        if (out and out[-1].startswith("--") and "=" not in out[-1] and out[-1] != "--"
                and _NEGATIVE_VALUE.match(arg)):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def parser() -> argparse.ArgumentParser:
    """Every subcommand: `run`, the client's (cli.task_verbs) and each tool's own (its add_parser)."""
    from tecdard.cli.task_verbs import add_parsers
    from tecdard.tools import calibrate, demo, doctor, export, imu, kernel_cache, localize, plot, sim_record
    top = argparse.ArgumentParser(prog="tecdard", description="Transient extrinsic contact detection and ranging daemon")
    top.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = top.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run the daemon")
    p.add_argument("--config", required=True, help="YAML configuration file")
    p.add_argument("--listen", help="Zenoh endpoint to listen on, overrides zenoh.listen (e.g. tcp/127.0.0.1:7507)")
    p.set_defaults(func=_cmd_run)
    for tool in (localize, plot, export, calibrate, sim_record, imu):
        tool.add_parser(sub)
    add_parsers(sub)
    for tool in (doctor, kernel_cache, demo):
        tool.add_parser(sub)
    return top


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(join_negative_values(sys.argv[1:] if argv is None else list(argv)))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    return args.func(args)
