"""What the offline tools share on the command line: a bad input as one line (exit 2), and a recording
with the pipeline that replays it, from the tool's arguments."""
from __future__ import annotations

import sys

from tecdard.safejson import show


def refused(command: str, msg: str) -> int:
    """A command's bad input: one line on stderr naming the command, and exit status 2."""
    print(f"tecdard {command}: {msg}", file=sys.stderr)
    return 2


class BadInput(Exception):
    """A command-line tool's input that cannot be used; the message is one line (exit 2)."""


def show_path_error(exc) -> str:
    """A tecdard.files.OutputError as the tools say it: the option, then why (paths escaped, cut)."""
    return f"{exc.what}: {show(exc.reason, 300)[1:-1]}" if isinstance(exc.reason, str) else str(exc)


def add_replay_options(p) -> None:
    """What every tool that replays a recording takes (recording_and_pipeline reads them): the
    recording, the estimator, the config that tunes the pipeline, and --ignore-live."""
    p.add_argument("recording", help="REC.npz")
    p.add_argument("--method", help="estimator (default: the config's, else ekf); an unknown name lists them all")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline")
    p.add_argument("--ignore-live", action="store_true",
                   help="a daemon recording: replay it as any recording, not as its live estimator was fed")


def checked_method(args) -> str | None:
    """args.method, if it names an estimator (None: the config's); BadInput listing them otherwise."""
    from tecdard.control import estimators
    method = getattr(args, "method", None)
    if method is not None and method not in estimators.names():
        raise BadInput(f"--method: unknown estimator {show(method)} (known: {', '.join(estimators.names())})")
    return method


def recording_and_pipeline(args):
    """The recording named by args.recording, its live_* log (None for any other, or with
    --ignore-live) and a contact pipeline from args.config's `estimator` section; BadInput otherwise."""
    from tecdard.recording.replay import ReplayError, open_replay

    method = checked_method(args)
    try:
        r = open_replay(args.recording, args.config, method, getattr(args, "ignore_live", False),
                        getattr(args, "no_plane", False))
    except ReplayError as exc:
        raise BadInput(str(exc)) from None
    return r.rec, r.live, r.pipeline


def estimates(args, rec, live, pipeline, rate_hz: float = 1000.0, on_estimate=None, on_event=None):
    """(rows, onset_t, last) of the replay: as fed live for a daemon recording, else causally in chunks."""
    from tecdard.recording.replay import Replay, ReplayError, run_replay
    try:
        return run_replay(Replay(rec, live, pipeline, str(args.recording)), rate_hz, on_estimate, on_event)
    except ReplayError as exc:
        raise BadInput(str(exc)) from None
