"""`tecdard <verb>`: drive a running daemon over Zenoh (the task verbs of tecdard/verbs/, stop, status, cancel)."""
from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import json
import math
import os
import sys
import time

from tecdard import verbs
from tecdard.api.commands import task_verbs
from tecdard.api.session import (DAEMON_NAME, DEFAULT_ENDPOINT, TlsFiles, endpoint_problem, endpoint_refused,
                                  speaks_tls)
from tecdard.cli import show
from tecdard.api.client import Client, ClientError, Denied
from tecdard.safejson import first_line

EXIT_DONE, EXIT_FAILED, EXIT_REFUSED, EXIT_NO_DAEMON, EXIT_DENIED = 0, 1, 2, 3, 4


def _finite(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return x


def _vec(text: str) -> list[float]:
    try:
        out = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(math.isfinite(x) for x in out):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return out


def _ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


# the control verbs' options (option, payload field, type, help, choices); a task verb's come from its fields
CONTROL_OPTIONS = {"stop": [], "status": [],
                   "cancel": [("--task", "task", str, "task id (default: the running task)", None)],
                   "record": [("--action", "action", str, "start or stop a capture on demand", ("start", "stop")),
                              ("--label", "label", str, "a label for the file's name", None)],
                   "grasp": [("--force", "force", _finite, "the grip force, N (default gripper.force_n; at most "
                                                           "gripper.max_force_n); eta is looked up by it", None),
                             ("--width", "width", _finite, "the object's width between the fingers, m (default "
                                                           "gripper.width_m; Franka Hand)", None),
                             ("--speed", "speed", _finite, "the fingers' speed, m/s (default gripper.speed_m_s)", None)],
                   "release": [("--width", "width", _finite, "the opening to move to, m (default "
                                                             "gripper.open_width_m)", None),
                               ("--speed", "speed", _finite, "the fingers' speed, m/s (default gripper.speed_m_s)",
                                None)],
                   "recover": []}
CONTROL_SUMMARIES = {"stop": "stop the arm now, whatever runs (always allowed)",
                     "status": "the daemon's mode, task, faults, TCP and contact (mm, deg)",
                     "cancel": "end the running task as stop does, and report it failed",
                     "record": "start or stop a recording on demand",
                     "grasp": "close the gripper on the object at a grip force (never during a task)",
                     "release": "open the gripper (never during a task); tasks then refuse until a grasp",
                     "recover": "return the arm to where tasks run (unlock a protective stop, franky's error "
                                "recovery), or say what a person must do"}
CONTROL_EXAMPLES = {"stop": "tecdard stop", "status": "tecdard status --robot ur5e-left",
                    "cancel": "tecdard cancel", "record": "tecdard record --action start --label hinge-a",
                    "grasp": "tecdard grasp --force 30", "release": "tecdard release", "recover": "tecdard recover"}
FIELD_TYPES = {"number": _finite, "direction": _vec, "numbers": _vec, "choice": str, "bool": bool, "grid": _ints,
               "int_choice": int}
ENV_CONNECT, ENV_ROBOT = "TECDAR_CONNECT", "TECDAR_ROBOT"
HELP_STATUS_S = 0.5           # --help asks a running daemon for its limits this long at most
CANCEL_WAIT_S = 10.0          # after a cancel, how long to wait for the task to end and the arm to brake
BRAKE_POLL_S = 0.05           # how often `status` is asked whether the arm has braked
EXIT_INTERRUPTED = 130


def default_connect() -> str:
    return os.environ.get(ENV_CONNECT) or DEFAULT_ENDPOINT


def default_robot() -> str:
    return os.environ.get(ENV_ROBOT) or "sim"


def _show(value, unit: str) -> str:
    if isinstance(value, (list, tuple)):
        return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in value) + (f" {unit}" if unit else "")
    if isinstance(value, float):
        return f"{value:g}" + (f" {unit}" if unit else "")
    return str(value) + (f" {unit}" if unit and not isinstance(value, str) else "")


def field_help(f, limits) -> str:
    """A field's help: what it is, its unit, default and limits (the daemon's where it answered)."""
    parts = [f.help or f.name]
    if f.unit:
        parts.append(f"unit {f.unit}")
    default = f.resolve("default", limits)
    if default is verbs.REQUIRED:
        parts.append("required")
    elif default is not None and f.kind != "bool":
        parts.append(f"default {_show(default, f.unit)}")
    lo, hi = f.resolve("lo", limits), f.resolve("hi", limits)
    if lo is not None and hi is not None:
        parts.append(f"limits {_show(lo, '')}..{_show(hi, f.unit)}")
    return "; ".join(parts).replace("%", "%%")


def help_limits(argv: list[str]):
    """The limits --help shows: a running daemon's (its `status` reply), else the shipped defaults;
    and a note saying which."""
    from tecdard.api.commands import Limits
    endpoint, robot = default_connect(), default_robot()
    for i, arg in enumerate(argv[:-1]):
        if arg == "--connect":
            endpoint = argv[i + 1]
        elif arg == "--robot":
            robot = argv[i + 1]
    for arg in argv:
        if arg.startswith("--connect="):
            endpoint = arg.split("=", 1)[1]
        elif arg.startswith("--robot="):
            robot = arg.split("=", 1)[1]
    shipped = f"limits: the shipped defaults (no daemon {robot} answered at {endpoint})"
    if endpoint_problem(endpoint) or endpoint.startswith("tls/"):
        return Limits(), shipped
    try:
        with Client(endpoint, robot=robot, open_timeout_s=HELP_STATUS_S) as cli:
            reply = cli.command("status", None, timeout=HELP_STATUS_S)
        theirs = reply.get("limits") if isinstance(reply, dict) else None
        known = {f.name for f in dataclasses.fields(Limits)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in (theirs or {}).items() if k in known}
        return Limits(**values), f"limits: the running daemon's ({robot} at {endpoint})"
    except Exception:
        return Limits(), shipped


def verb_options() -> dict[str, list[tuple]]:
    """verb -> [(option, payload field, type, help, choices)], the task verbs' from their registered fields."""
    out = {}
    for spec in verbs.discover().values():
        out[spec.name] = [(f.option, f.name, FIELD_TYPES[f.kind], f.help or f.unit, f.choices or None)
                          for f in spec.fields]
    return {**out, **CONTROL_OPTIONS}


def add_parsers(sub, limits=None, limits_note: str = "") -> None:
    from tecdard.api.commands import Limits
    limits = limits or Limits()
    specs = verbs.discover()
    summaries = {**{v.name: v.summary for v in specs.values()}, **CONTROL_SUMMARIES}
    examples = {**{v.name: v.example for v in specs.values()}, **CONTROL_EXAMPLES}
    for verb, fields in verb_options().items():
        is_task = verb in specs
        epilog = "\n".join(x for x in (f"example: {examples.get(verb)}" if examples.get(verb) else "",
                                        limits_note if is_task else "",
                                        "Ctrl-C cancels the task it started and waits for the arm to stop "
                                        "(exit 130)." if is_task else "") if x)
        p = sub.add_parser(verb, help=summaries.get(verb, f"send '{verb}' to a running daemon"),
                           description=summaries.get(verb), epilog=epilog,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("--connect", default=default_connect(),
                       help=f"daemon endpoint (default %(default)s; ${ENV_CONNECT} sets it)")
        p.add_argument("--robot", default=default_robot(),
                       help=f"robot name in the key expressions (default %(default)s; ${ENV_ROBOT} sets it)")
        p.add_argument("--timeout", type=_finite, default=120.0,
                       help="seconds to wait for the task to end; a task still running then is cancelled "
                            "(default %(default)g s)")
        p.add_argument("--wait-alive", type=_finite, default=None,
                       help="seconds to wait for the daemon to be ready (its liveliness token; "
                            "default: --timeout, at most 10)")
        p.add_argument("--json", action="store_true", help="print replies and events as JSON lines (SI units)")
        add_tls_options(p, "the daemon's (or of the router's, through one)", "client's certificate (its CN may be a "
                        "commander)")
        if is_task:
            p.add_argument("--no-follow", action="store_true",
                           help="return once the task is accepted (it runs on; `tecdard cancel` ends it)")
            fields_by_option = {f.option: f for f in specs[verb].fields}
        for opt, _field, typ, help_, choices in fields:
            f = fields_by_option.get(opt) if is_task else None
            text = field_help(f, limits) if f is not None else help_
            if typ is bool:
                p.add_argument(opt, action=argparse.BooleanOptionalAction, default=None, help=text)
            else:
                p.add_argument(opt, type=typ, help=text, choices=choices,
                               metavar=None if choices else opt.lstrip("-").replace("-", "_").upper())
        p.set_defaults(func=run_verb, verb=verb)


class Progress:
    """The progress line on stderr: rewritten in place on a terminal (cleared between phases, so no
    residue of a longer line stays), else one line per phase and at most one every few seconds."""

    EVERY_S = 5.0

    def __init__(self, out):
        self.out, self.tty = out, out.isatty()
        self.start_p = None
        self.phase = None
        self.last_t = -math.inf
        self.shown = False

    def update(self, state: dict | None) -> None:
        if state is None:
            return
        p = (state.get("tcp") or {}).get("p")
        if self.start_p is None and isinstance(p, list) and len(p) == 3:
            self.start_p = p
        text = show.progress_text(state, self.start_p)
        if text is None:
            return
        phase = (state.get("task") or {}).get("phase")
        now = time.monotonic()
        if self.tty:
            if phase != self.phase and self.shown:
                print("\r\033[K", end="", file=self.out)
            print(f"\r\033[K{text}", end="", file=self.out, flush=True)
        elif phase != self.phase or now - self.last_t >= self.EVERY_S:
            print(text, file=self.out, flush=True)
            self.last_t = now
        self.phase, self.shown = phase, True

    def clear(self) -> None:
        if self.tty and self.shown:
            print("\r\033[K", end="", file=self.out, flush=True)
        self.shown = False


def _say(verb: str, text: str) -> None:
    print(f"tecdard {verb}: {text}", file=sys.stderr, flush=True)


def _not_alive_cause(args, tls) -> str:
    """The likely cause of a daemon not seen at the endpoint, where one can be told: a tcp/ endpoint where a TLS
    router listens, a certificate a roster's router lets see nothing, another robot's name."""
    if speaks_tls(args.connect):
        host_port = args.connect.partition("/")[2]
        return (f"; {args.connect} speaks TLS: connect with tls/{host_port} and --tls-ca, --tls-cert and --tls-key")
    if tls is not None:
        other = _missing_robot(args, tls)
        if other:
            return other
        return ("; no robot's token at all is visible through it: if the router enforces the fleet's roster, is "
                f"the name of --tls-cert {tls.cert} on it? (a certificate of the fleet's CA not on the roster "
                "connects, and is shown nothing)")
    return _missing_robot(args, tls)


def _missing_robot(args, tls) -> str:
    """Which robot names answer at the endpoint, for a robot that does not."""
    try:
        with Client(args.connect, robot="*", tls=tls, daemon_name=args.tls_daemon_name, open_timeout_s=1.0) as cli:
            names = cli.robots_alive(1.0)
    except Exception:
        return ""
    if not names or names == [args.robot]:
        return ""
    return f"; robots that answer at {args.connect}: {', '.join(names)} (--robot or ${ENV_ROBOT})"


def _cancel(cli: Client, args, task: str | None, why: str) -> str:
    """Cancel the task this command started and wait for it to end: the one line that says how it went."""
    if task is None:
        return f"{why}; nothing was started"
    try:
        reply = cli.command("cancel", {"task": task}, timeout=5.0)
    except ClientError as exc:
        return f"{why}; could not cancel task {task} ({exc}): `tecdard stop` stops the arm"
    if not reply.get("ok"):
        code = (reply.get("error") or {}).get("code")
        if code == "no_task":                    # the Ctrl-C and the task's end crossed: say how it ended
            return f"{why}; task {task} had already ended: {_how_it_ended(cli, task)}"
        return f"{why}; cancel of task {task} refused ({code}): `tecdard stop` stops the arm"
    deadline = time.monotonic() + CANCEL_WAIT_S
    try:
        cli.wait_event(("task_done", "task_failed"), task, timeout=CANCEL_WAIT_S)
    except ClientError:
        return (f"{why}; task {task} cancelled, but its end was not seen within {CANCEL_WAIT_S:g} s: "
                "`tecdard status`, and `tecdard stop` stops the arm")
    if not _braked(cli, deadline):
        return (f"{why}; task {task} cancelled, but the arm was still braking after {CANCEL_WAIT_S:g} s: "
                "`tecdard status`, and `tecdard stop` stops the arm")
    return f"{why}; task {task} cancelled and the arm stopped"


def _how_it_ended(cli: Client, task: str) -> str:
    """The task's end as this client saw it (its end event may be in flight still: briefly waited for)."""
    try:
        ev = next((e for e in reversed(cli.event_log) if e.get("task") == task
                   and e.get("kind") in ("task_done", "task_failed")), None) \
            or cli.wait_event(("task_done", "task_failed"), task, timeout=1.0)
    except ClientError:
        return "its end event was not seen (`tecdard status`)"
    return "done" if ev["kind"] == "task_done" else f"failed ({ev.get('error')})"


def _braked(cli: Client, deadline: float) -> bool:
    """Whether the daemon's mode left `busy` (a task that has ended is `busy` while the arm brakes)
    before `deadline` (monotonic s)."""
    while True:
        try:
            if cli.command("status", timeout=2.0)["state"]["mode"] != "busy":
                return True
        except (ClientError, KeyError, TypeError):
            pass
        if time.monotonic() >= deadline:
            return False
        time.sleep(BRAKE_POLL_S)


def _send(cli: Client, args, payload: dict):
    """Send the command on a worker thread so that Ctrl-C while it is under way still learns its
    reply (and so the task id to cancel)."""
    pool = concurrent.futures.ThreadPoolExecutor(1)
    fut = pool.submit(cli.command, args.verb, payload, min(args.timeout, 30.0))
    pool.shutdown(wait=False)
    return fut


def run_verb(args) -> int:
    payload = {field: getattr(args, opt.lstrip("-").replace("-", "_"))
               for opt, field, _t, _h, _c in verb_options()[args.verb]
               if getattr(args, opt.lstrip("-").replace("-", "_")) is not None}
    problem = endpoint_problem(args.connect)
    if problem:
        _say(args.verb, f"--connect {args.connect}: {problem}")
        return EXIT_REFUSED
    tls, problem = tls_files(args)
    if problem:
        _say(args.verb, problem)
        return EXIT_REFUSED
    refused = endpoint_refused(args.connect)
    if refused:                                  # said at once, not after the liveliness wait's 10 s
        _say(args.verb, refused)
        return EXIT_NO_DAEMON
    try:
        cli = Client(args.connect, robot=args.robot, tls=tls, daemon_name=args.tls_daemon_name)
    except Exception as exc:                      # zenoh refuses a file or a setting
        cause = _not_alive_cause(args, tls) if speaks_tls(args.connect) else ""
        _say(args.verb, f"cannot open a session to {args.connect}: {first_line(exc)}{cause}")
        return EXIT_NO_DAEMON
    task = None
    sent = None
    with cli:
        try:
            try:
                wait_s = args.wait_alive if args.wait_alive is not None else min(args.timeout, 10.0)

                def waiting(s: float) -> None:
                    if s < 1.5 and speaks_tls(args.connect):     # a plain tcp/ to a TLS router: said at once
                        raise ClientError(f"no session at {args.connect}{_not_alive_cause(args, tls)}")
                    _say(args.verb, f"waiting up to {wait_s:g} s for the daemon's liveliness token "
                                    f"{cli.keys.alive} at {args.connect} ({s:.0f} s so far)")
                cli.wait_alive(wait_s, waiting=waiting)
                sent = _send(cli, args, payload)
                reply = sent.result()
            except Denied as exc:                 # a denial reads as one, with its own exit code
                _say(args.verb, str(exc))
                return EXIT_DENIED
            except ClientError as exc:
                cause = _not_alive_cause(args, tls) if "not alive" in str(exc) else ""
                _say(args.verb, f"{exc}{cause}")
                return EXIT_NO_DAEMON
            return _answered(cli, args, reply)
        except KeyboardInterrupt:
            if args.verb not in task_verbs():
                _say(args.verb, "interrupted")
                return EXIT_INTERRUPTED
            if sent is not None:
                try:                              # the reply may be on its way: its task is the one to cancel
                    reply = sent.result(timeout=5.0)
                    task = reply.get("task") if reply.get("ok") else None
                except Exception:
                    task = None
            _say(args.verb, _cancel(cli, args, task, "interrupted"))
            return EXIT_INTERRUPTED


def _answered(cli: Client, args, reply: dict) -> int:
    if args.json:
        print(json.dumps(reply))
    elif args.verb == "status" and reply.get("ok") and isinstance(reply.get("state"), dict):
        print("\n".join(show.status_lines(reply["state"])))
    elif args.verb == "status" and reply.get("ok"):
        print("the daemon has no state yet (starting)")
    if not reply.get("ok"):
        err = reply.get("error", {})
        _say(args.verb, f"refused: {err.get('code')}: {err.get('message')}")
        return EXIT_REFUSED
    if args.verb not in task_verbs():
        if not args.json and isinstance(reply.get("gripper"), dict):
            print(f"{args.verb}: ok, {show.gripper_text(reply['gripper'])}")
        elif not args.json and isinstance(reply.get("steps"), list):          # recover: what it did
            print(f"{args.verb}: ok: " + "; ".join(str(s) for s in reply["steps"]))
        elif not args.json and args.verb != "status":
            print(f"{args.verb}: ok")
        return EXIT_DONE
    task = reply["task"]
    if not args.json:
        print(f"{args.verb}: accepted as task {task}")
        if isinstance(reply.get("direction_from"), str):          # a rotate after a rotate: which way it probes
            shown = ", ".join(f"{float(x):.3f}" for x in reply.get("direction") or [])
            print(f"{args.verb}: direction {shown or 'the configured default'}: {reply['direction_from']}")
    if args.no_follow:
        return EXIT_DONE
    progress = Progress(sys.stderr)
    try:
        ev = _follow(cli, args, task, progress)
    except KeyboardInterrupt:
        progress.clear()
        _say(args.verb, _cancel(cli, args, task, "interrupted"))
        return EXIT_INTERRUPTED
    progress.clear()
    if ev is None:
        _say(args.verb, _cancel(cli, args, task, f"still running after --timeout {args.timeout:g} s"))
        return EXIT_FAILED
    if args.json:
        print(json.dumps(ev))
    elif ev["kind"] == "task_done":
        print("\n".join(show.result_lines(args.verb, ev.get("result") or {})))
    if ev["kind"] == "task_done":
        return EXIT_DONE
    _say(args.verb, f"task failed: {ev.get('error')}")
    return EXIT_FAILED


def _follow(cli: Client, args, task: str, progress: Progress) -> dict | None:
    """The task's end event, or None once --timeout has passed."""
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline:
        try:
            return cli.wait_event(("task_done", "task_failed"), task, timeout=0.2)
        except ClientError:
            state = None
            while not cli.states.empty():
                state = cli.states.get_nowait()
            if not args.json:
                progress.update(state)
    return None


def add_tls_options(p, peer: str, mine: str) -> None:
    """--tls-ca, --tls-cert, --tls-key and --tls-daemon-name (tls_files reads them): `peer` names whose
    certificate the CA signed and the name checks, `mine` this end's certificate."""
    p.add_argument("--tls-ca", help=f"with a tls/ endpoint: the CA that signed {peer} certificate")
    p.add_argument("--tls-cert", help=f"with a tls/ endpoint: this {mine}")
    p.add_argument("--tls-key", help="with a tls/ endpoint: the private key of --tls-cert")
    p.add_argument("--tls-daemon-name", default=DAEMON_NAME, metavar="CN",
                   help=f"with a tls/ endpoint: the common name of {peer} certificate; nothing else is answered "
                        "or listened to (default %(default)s)")


def tls_files(args) -> tuple[TlsFiles | None, str | None]:
    """(the TLS files of add_tls_options' options or None for none, what is wrong with them or None)."""
    given = [x for x in (args.tls_ca, args.tls_cert, args.tls_key) if x]
    if given and len(given) != 3:
        return None, "--tls-ca, --tls-cert and --tls-key go together"
    if not given and str(getattr(args, "connect", "")).startswith("tls/"):
        # without them the TLS handshake never completes, and the wait for the daemon read as a dead daemon
        return None, (f"--connect {args.connect}: a tls/ endpoint needs --tls-ca, --tls-cert and --tls-key (your "
                      "certificate, its key, and the CA of the fleet: docs/fleet.md)")
    return (TlsFiles(args.tls_ca, args.tls_cert, args.tls_key) if given else None), None
