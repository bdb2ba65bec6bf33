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
    from tecdard.robots.backends import BackendError, ModelMismatch
    try:
        return daemon.run()
    except ModelMismatch as exc:
        print(f"tecdard: config error: {exc}", file=sys.stderr)
        return 2
    except BackendError as exc:
        print(f"tecdard: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:        # zenoh.ZError: cannot listen (address in use, no such interface)
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        from tecdard.runtime.network import listen_error
        print(f"tecdard: {listen_error(exc, daemon.zenoh.listen)}", file=sys.stderr)
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


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors as one line naming the option, and where help is (not a usage dump)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (`{self.prog} --help`)\n")


def parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """Every subcommand: `run`, the client's (cli.task_verbs) and each tool's own (its add_parser).
    With --help in `argv`, the task verbs' limits are a running daemon's where one answers."""
    from tecdard.cli.task_verbs import add_parsers, help_limits, verb_options
    from tecdard.tools import (calibrate, calibrate_mount, demo, doctor, export, fake_board, imu, import_log,
                               kernel_cache, localize, plot, report, sim_record)
    from tecdard.cli import episodes, fleet, options, router
    argv = argv or []
    limits, note = None, ""
    if ("-h" in argv or "--help" in argv) and argv and argv[0] in verb_options():
        limits, note = help_limits(argv)
    top = OneLineParser(prog="tecdard", description="Transient extrinsic contact detection and ranging daemon")
    top.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = top.add_subparsers(dest="cmd", required=True)
    wants_help = "-h" in argv or "--help" in argv
    p = sub.add_parser("run", help="run the daemon", formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog=run_epilog() if wants_help and argv[:1] == ["run"] else None)
    p.add_argument("--config", required=True, help="YAML configuration file (its options: `tecdard options`, "
                                                   "and below with --help)")
    p.add_argument("--listen", help="Zenoh endpoint to listen on, overrides zenoh.listen (e.g. tcp/127.0.0.1:7507)")
    p.set_defaults(func=_cmd_run)
    for tool in (localize, plot, export, calibrate, calibrate_mount, import_log, sim_record, imu, fake_board):
        tool.add_parser(sub)
    add_parsers(sub, limits, note)
    for tool in (doctor, report, kernel_cache, demo, options, fleet, router, episodes):
        tool.add_parser(sub)
    return top


def run_epilog() -> str:
    """`tecdard run --help`'s end: every config option with its default, unit and limits."""
    from tecdard.cli.options import text
    return "config options (section.key = default unit (limits): what it does):\n" + text()


def warm_parser() -> argparse.ArgumentParser:
    """`tecdard warm` alone: the whole parser imports the tools and, through them, the estimator's
    kernels, which (before they are built ahead of time) would compile them with numba's JIT first."""
    from tecdard.tools import kernel_cache
    top = argparse.ArgumentParser(prog="tecdard")
    kernel_cache.add_parser(top.add_subparsers(dest="command", required=True))
    return top


def main(argv: list[str] | None = None) -> int:
    argv = join_negative_values(sys.argv[1:] if argv is None else list(argv))
    if argv[:1] == ["warm"]:
        args = warm_parser().parse_args(argv)
        return args.func(args)
    try:
        top = parser(argv)             # imports the tools, and with them the estimator's kernels
    except ImportError as exc:
        if type(exc).__name__ != "KernelsUnavailable":
            raise
        print(f"tecdard: {exc}", file=sys.stderr)
        return 2
    args = top.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return args.func(args)
    except KeyboardInterrupt:          # a verb that does not handle Ctrl-C itself: one line, no traceback
        verb = next((a for a in argv if not a.startswith("-")), "")
        print(f"tecdard {verb}: interrupted", file=sys.stderr)
        return 130
