"""`tecdard <verb>`: drive a running daemon over Zenoh (the task verbs of tecdard/verbs/, stop, status, cancel)."""
from __future__ import annotations

import argparse
import json
import sys
import time

from tecdard.cli.client import Client, ClientError
from tecdard import verbs
from tecdard.api.commands import task_verbs
from tecdard.api.session import DAEMON_NAME, DEFAULT_ENDPOINT, TlsFiles

EXIT_DONE, EXIT_FAILED, EXIT_REFUSED, EXIT_NO_DAEMON = 0, 1, 2, 3
BAR_WIDTH = 30


def _vec(text: str) -> list[float]:
    try:
        out = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    return out


def _ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


# the control verbs' options; a task verb's come from its fields (tecdard/verbs/)
CONTROL_OPTIONS = {"stop": [], "status": [],
                   "cancel": [("--task", "task", str, "task id (default: the running task)")],
                   "record": [("--action", "action", str, "start or stop a capture on demand"),
                              ("--label", "label", str, "a label for the file's name")]}
FIELD_TYPES = {"number": float, "direction": _vec, "numbers": _vec, "choice": str, "bool": bool, "grid": _ints,
               "int_choice": int}


def verb_options() -> dict[str, list[tuple]]:
    """verb -> [(option, payload field, type, help)], the task verbs' from their registered fields."""
    out = {}
    for spec in verbs.discover().values():
        out[spec.name] = [(f.option, f.name, FIELD_TYPES[f.kind], f.help or f.unit) for f in spec.fields]
    return {**out, **CONTROL_OPTIONS}


def add_parsers(sub) -> None:
    summaries = {v.name: v.summary for v in verbs.discover().values()}
    for verb, fields in verb_options().items():
        p = sub.add_parser(verb, help=summaries.get(verb, f"send '{verb}' to a running daemon"))
        p.add_argument("--connect", default=DEFAULT_ENDPOINT, help=f"daemon endpoint (default {DEFAULT_ENDPOINT})")
        p.add_argument("--robot", default="sim", help="robot name in the key expressions (default sim)")
        p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the task to end")
        p.add_argument("--wait-alive", type=float, default=None,
                       help="seconds to wait for the daemon to be ready (its liveliness token; "
                            "default: --timeout, at most 10)")
        p.add_argument("--json", action="store_true", help="print replies and events as JSON lines")
        p.add_argument("--tls-ca", help="with a tls/ endpoint: the CA that signed the daemon's certificate")
        p.add_argument("--tls-cert", help="with a tls/ endpoint: this client's certificate (its CN may be a commander)")
        p.add_argument("--tls-key", help="with a tls/ endpoint: this client's private key")
        p.add_argument("--tls-daemon-name", default=DAEMON_NAME, metavar="CN",
                       help="with a tls/ endpoint: the common name of the daemon's certificate (or of the router's, "
                            "through one); nothing else is answered or listened to (default %(default)s)")
        if verb in summaries:
            p.add_argument("--no-follow", action="store_true", help="return once the task is accepted")
        for opt, _field, typ, help_ in fields:
            if typ is bool:
                p.add_argument(opt, action=argparse.BooleanOptionalAction, default=None, help=help_)
            else:
                p.add_argument(opt, type=typ, help=help_)
        p.set_defaults(func=run_verb, verb=verb)


def _progress(state: dict | None, out) -> None:
    task = (state or {}).get("task")
    if not task:
        return
    frac = max(0.0, min(1.0, float(task.get("progress", 0.0))))
    filled = int(round(frac * BAR_WIDTH))
    bar = "#" * filled + "." * (BAR_WIDTH - filled)
    end = "\r" if out.isatty() else "\n"
    print(f"[{bar}] {frac * 100:5.1f}% {task.get('phase', '')}", end=end, file=out, flush=True)


def run_verb(args) -> int:
    payload = {field: getattr(args, opt.lstrip("-").replace("-", "_"))
               for opt, field, _t, _h in verb_options()[args.verb]
               if getattr(args, opt.lstrip("-").replace("-", "_")) is not None}
    given = [x for x in (args.tls_ca, args.tls_cert, args.tls_key) if x]
    if given and len(given) != 3:
        print(f"tecdard {args.verb}: --tls-ca, --tls-cert and --tls-key go together", file=sys.stderr)
        return EXIT_REFUSED
    tls = TlsFiles(args.tls_ca, args.tls_cert, args.tls_key) if given else None
    try:
        cli = Client(args.connect, robot=args.robot, tls=tls, daemon_name=args.tls_daemon_name)
    except Exception as exc:                      # zenoh refuses a malformed endpoint
        print(f"tecdard {args.verb}: cannot open a session to {args.connect}: {exc}", file=sys.stderr)
        return EXIT_NO_DAEMON
    with cli:
        try:
            wait_s = args.wait_alive if args.wait_alive is not None else min(args.timeout, 10.0)
            cli.wait_alive(wait_s, waiting=lambda s: print(
                f"tecdard {args.verb}: waiting up to {wait_s:g} s for the daemon's liveliness token "
                f"{cli.keys.alive} at {args.connect} ({s:.0f} s so far)", file=sys.stderr, flush=True))
            reply = cli.command(args.verb, payload, timeout=min(args.timeout, 30.0))
        except ClientError as exc:
            print(f"tecdard {args.verb}: {exc}", file=sys.stderr)
            return EXIT_NO_DAEMON
        if args.json or args.verb == "status":
            print(json.dumps(reply))
        if not reply.get("ok"):
            err = reply.get("error", {})
            print(f"tecdard {args.verb}: refused: {err.get('code')}: {err.get('message')}", file=sys.stderr)
            return EXIT_REFUSED
        if args.verb not in task_verbs():
            if not args.json and args.verb != "status":
                print(f"{args.verb}: ok")
            return EXIT_DONE
        task = reply["task"]
        if not args.json:
            print(f"{args.verb}: accepted as task {task}")
        if args.no_follow:
            return EXIT_DONE
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            try:
                ev = cli.wait_event(("task_done", "task_failed"), task, timeout=0.2)
            except ClientError:
                state = None
                while not cli.states.empty():
                    state = cli.states.get_nowait()
                if not args.json:
                    _progress(state, sys.stderr)
                continue
            if sys.stderr.isatty():
                print(file=sys.stderr)
            if args.json:
                print(json.dumps(ev))
            elif ev["kind"] == "task_done":
                print(f"{args.verb} done: {json.dumps(ev.get('result', {}))}")
            if ev["kind"] == "task_done":
                return EXIT_DONE
            print(f"tecdard {args.verb}: task failed: {ev.get('error')}", file=sys.stderr)
            return EXIT_FAILED
        print(f"tecdard {args.verb}: no task_done or task_failed within {args.timeout:g} s", file=sys.stderr)
        return EXIT_FAILED
