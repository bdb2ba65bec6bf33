"""`tecdard localize REC.npz`: replay a recording through the contact pipeline, causally, as the daemon would
(tecdard.recording.replay); this module is its command line and its output."""
from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:        # the pipeline (and its compiled kernels) loads when a replay runs, not for --help
    from tecdard.control.pipeline import ContactEstimate

from tecdard.tools.args import BadInput, add_replay_options, estimates, recording_and_pipeline, refused, show_path_error

EXIT_OK, EXIT_NO_CONTACT, EXIT_BAD_INPUT = 0, 1, 2


CSV_ROW = "%.9f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f\n"


def write_csv(out, rows: np.ndarray) -> None:
    """The rows as `t,px,py,pz,sx,sy,sz` to a path or an open text file."""
    if isinstance(out, (str, bytes)) or hasattr(out, "__fspath__"):
        with open(out, "w") as f:
            write_csv(f, rows)
        return
    out.write("t,px,py,pz,sx,sy,sz\n")
    # one %-format per row over Python floats, written once: a third of the per-row f-string's time
    out.write("".join(map(CSV_ROW.__mod__, map(tuple, np.asarray(rows, dtype=float).tolist()))))


def summary(onset_t: float, est: ContactEstimate) -> dict:
    return {"onset_t": onset_t, "p_c": est.p.tolist(), "std": est.std.tolist(), "method": est.method}


def print_summary(s: dict, as_json: bool, out=None) -> None:
    out = out or sys.stdout       # looked up at the call: sys.stdout may have been replaced since import
    if as_json:
        print(json.dumps(s), file=out)
    else:
        p = ", ".join(f"{x:.4f}" for x in s["p_c"])
        sd = ", ".join(f"{x * 1e3:.1f}" for x in s["std"])
        print(f"onset {s['onset_t']:.4f} s; contact [{p}] m, one-sigma [{sd}] mm ({s['method']})", file=out)


MAX_RATE_HZ = 100_000.0      # --rate: more rows per second than any IMU delivers is a typo


def add_parser(sub) -> None:
    p = sub.add_parser("localize", help="estimate the contact in a recording (tecdar-recording/1)")
    add_replay_options(p)
    p.add_argument("--out", help="write estimates as CSV: t,px,py,pz,sx,sy,sz")
    p.add_argument("--rate", type=float, default=1000.0, help="at most this many rows per second (default 1000)")
    p.add_argument("--json", action="store_true", help="print the summary as a JSON object")
    p.add_argument("--no-plane", action="store_true", help="ignore plane_normal: use the 3D estimator")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard localize`: exit 0 (a contact), 1 (none) or 2 (bad input, one line)."""
    from tecdard.files import OutputError, check_output, replacing

    def bad(msg: str) -> int:
        return refused("localize", msg)

    if not 0 < args.rate <= MAX_RATE_HZ:
        return bad(f"--rate: must be in (0, {MAX_RATE_HZ:g}] rows per second, got {args.rate:g}")
    try:
        if args.out:
            check_output(args.out, "--out", [args.recording])      # before the replay: a bad path fails at once
        rec, live, pipeline = recording_and_pipeline(args)
        rows, onset_t, last = estimates(args, rec, live, pipeline, args.rate)
        if args.out:
            with replacing(args.out, "--out") as tmp:        # whole or not at all: a full disk leaves the old one
                write_csv(tmp, rows)
    except BadInput as exc:
        return bad(str(exc))
    except OutputError as exc:
        return bad(show_path_error(exc))
    if onset_t is None or last is None:
        if args.json:
            print(json.dumps({"onset_t": None, "p_c": None, "std": None, "method": pipeline.method}))
        print("tecdard localize: no contact detected", file=sys.stderr)
        return EXIT_NO_CONTACT
    print_summary(summary(onset_t, last), args.json)
    return EXIT_OK
