"""`tecdard calibrate-mount --live`: the recording the mount is fitted from, made by a running daemon.

A capture on demand (`record start`, label `mount-calibration`), the `wrist` task (the gripper turned
in place about each TCP axis: at most +-10 deg at 5 deg/s by default, within limits.max_rotation_deg,
the TCP held where it is), `record stop`, then the `recording_written` event's file. Ctrl-C cancels
the task and ends the capture (exit 130); a refusal or a failed task is one line (exit 2, 1).
"""
from __future__ import annotations

import os
import sys
import time

from tecdard.api.client import Client, ClientError
from tecdard.api.session import DAEMON_NAME, TlsFiles, endpoint_problem

LABEL = "mount-calibration"
WRITE_WAIT_S = 30.0           # the recording is written (compressed) this long after `record stop` at most
EXIT_FAILED, EXIT_REFUSED, EXIT_INTERRUPTED = 1, 2, 130


def add_options(p) -> None:
    from tecdard.api.session import DEFAULT_ENDPOINT
    p.add_argument("--live", action="store_true", help="have a running daemon turn the wrist about each TCP axis "
                                                       "and record it, then fit that recording (needs no REC)")
    p.add_argument("--connect", default=os.environ.get("TECDAR_CONNECT") or DEFAULT_ENDPOINT,
                   help="with --live: the daemon's endpoint (default %(default)s)")
    p.add_argument("--robot", default=os.environ.get("TECDAR_ROBOT") or "sim",
                   help="with --live: the robot's name (default %(default)s)")
    p.add_argument("--amplitude-deg", type=float, default=10.0,
                   help="with --live: how far the wrist turns each way about each axis, deg (1..10, and within "
                        "limits.max_rotation_deg; default 10)")
    p.add_argument("--rate-deg-s", type=float, default=5.0, help="with --live: deg/s (1..20; default 5)")
    p.add_argument("--timeout", type=float, default=120.0, help="with --live: seconds the task may take (default 120)")
    p.add_argument("--tls-ca", help="with --live and a tls/ endpoint: the CA that signed the daemon's certificate")
    p.add_argument("--tls-cert", help="with --live and a tls/ endpoint: this client's certificate")
    p.add_argument("--tls-key", help="with --live and a tls/ endpoint: its private key")
    p.add_argument("--tls-daemon-name", default=DAEMON_NAME, metavar="CN",
                   help="with --live and a tls/ endpoint: the daemon certificate's common name (default %(default)s)")


def _say(text: str) -> None:
    print(f"tecdard calibrate-mount --live: {text}", file=sys.stderr)


def record(args) -> tuple[int, str | None]:
    """(exit code, the recording's path or None): the wrist's turns recorded by the daemon."""
    problem = endpoint_problem(args.connect)
    if problem:
        _say(f"--connect {args.connect}: {problem}")
        return EXIT_REFUSED, None
    given = [x for x in (args.tls_ca, args.tls_cert, args.tls_key) if x]
    if given and len(given) != 3:
        _say("--tls-ca, --tls-cert and --tls-key go together")
        return EXIT_REFUSED, None
    tls = TlsFiles(args.tls_ca, args.tls_cert, args.tls_key) if given else None
    with Client(args.connect, robot=args.robot, tls=tls, daemon_name=args.tls_daemon_name) as cli:
        task = None
        try:
            cli.wait_alive(min(args.timeout, 10.0))
            reply = cli.command("record", {"action": "start", "label": LABEL}, timeout=10.0)
            if not reply.get("ok"):
                return _refused("record start", reply), None
            reply = cli.command("wrist", {"amplitude_deg": args.amplitude_deg, "rate_deg_s": args.rate_deg_s},
                                timeout=10.0)
            if not reply.get("ok"):
                cli.command("record", {"action": "stop"}, timeout=10.0)
                return _refused("wrist", reply), None
            task = reply["task"]
            print(f"calibrate-mount --live: the wrist turns about each TCP axis (task {task}); keep clear of the tool",
                  file=sys.stderr)
            ev = cli.wait_event(("task_done", "task_failed"), task, timeout=args.timeout)
            task = None
            cli.command("record", {"action": "stop"}, timeout=10.0)
            if ev["kind"] != "task_done":
                _say(f"the wrist task failed: {ev.get('error')}")
                return EXIT_FAILED, None
            return 0, _written(cli)
        except KeyboardInterrupt:
            _say(_stop(cli, task, "interrupted"))
            return EXIT_INTERRUPTED, None
        except ClientError as exc:
            _say(_stop(cli, task, str(exc)))
            return EXIT_FAILED, None


def _refused(what: str, reply: dict) -> int:
    err = reply.get("error") or {}
    _say(f"{what} refused: {err.get('code')}: {err.get('message')}")
    return EXIT_REFUSED


def _written(cli: Client) -> str | None:
    deadline = time.monotonic() + WRITE_WAIT_S
    while time.monotonic() < deadline:
        ev = cli.wait_event(("recording_written",), None, timeout=max(deadline - time.monotonic(), 0.1))
        if ev.get("label") == LABEL:
            return str(ev.get("path"))
    return None


def _stop(cli: Client, task: str | None, why: str) -> str:
    """Cancel the task (if one runs) and end the capture: the one line that says how it went."""
    said = why
    try:
        if task is not None:
            reply = cli.command("cancel", {"task": task}, timeout=5.0)
            said += "; the wrist task cancelled" if reply.get("ok") else f"; cancel refused ({reply.get('error')})"
        cli.command("record", {"action": "stop"}, timeout=5.0)
    except (ClientError, KeyboardInterrupt) as exc:
        said += f"; could not reach the daemon ({exc}): `tecdard stop` stops the arm"
    return said
