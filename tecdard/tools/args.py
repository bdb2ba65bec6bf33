"""What the offline tools share on the command line: a bad input as one line (exit 2), and a recording
with the pipeline that replays it, from the tool's arguments."""
from __future__ import annotations

import logging
import sys

from tecdard.config import Config, ConfigError
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


def recording_and_pipeline(args):
    """The recording named by args.recording, its live_* log (None for any other, or with
    --ignore-live) and a contact pipeline from args.config's `estimator` section; BadInput otherwise."""
    from tecdard.control import estimators
    from tecdard.control.geometry import quat_to_matrix
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.format import RecordingError, load_live, load_recording

    method = getattr(args, "method", None)
    if method is not None and method not in estimators.names():
        raise BadInput(f"--method: unknown estimator {show(method)} (known: {', '.join(estimators.names())})")
    try:
        rec = load_recording(args.recording)
        live = None if getattr(args, "ignore_live", False) else load_live(args.recording, rec)
    except RecordingError as exc:
        raise BadInput(str(exc)) from None
    no_plane = getattr(args, "no_plane", False)
    try:
        cfg = Config.load(args.config) if args.config else Config({})
        section = cfg.section("estimator")
        pipeline = ContactPipeline.from_config(section, quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
                                  method=method, plane_normal=None if no_plane else rec.plane_normal)
        if no_plane:
            pipeline.params.plane_normal = None
        unused = section.unused_keys()
        if unused:
            raise ConfigError(f"{unused[0]}: unknown option")
    except ConfigError as exc:
        raise BadInput(f"config error: {exc}") from None
    return rec, live, pipeline


def estimates(args, rec, live, pipeline, rate_hz: float = 1000.0, on_estimate=None, on_event=None):
    """(rows, onset_t, last) of the replay: as fed live for a daemon recording, else causally in chunks."""
    from tecdard.tools import localize as L
    try:
        if live is not None:
            return L.replay_live(rec, live, pipeline, on_estimate)
        return L.replay(rec, pipeline, rate_hz, on_estimate=on_estimate, on_event=on_event)
    except Exception as exc:        # a recording the checks let through but the estimator cannot take
        logging.getLogger("tecdar").debug("replay failed", exc_info=True)
        raise BadInput(f"{show(args.recording, 200)}: could not be replayed ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:200] if str(exc) else ''}); please report it with the file") from None
