"""`tecdard localize REC.npz`: replay a recording through the contact pipeline, causally, as the daemon would."""
from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING

import numpy as np

from tecdard.control.geometry import quat_to_matrix
from tecdard.recording.format import LiveLog, Recording

if TYPE_CHECKING:        # the pipeline (and its compiled kernels) loads when a replay runs, not for --help
    from tecdard.control.pipeline import ContactEstimate, ContactPipeline

DIRECTIVE_FIELDS = ("episode", "armed", "arc_following", "bias_held", "begin_t", "since_t")

EXIT_OK, EXIT_NO_CONTACT, EXIT_BAD_INPUT = 0, 1, 2


def replay(rec: Recording, pipeline: ContactPipeline, rate_hz: float = 1000.0, chunk_s: float = 0.1,
           on_estimate=None, on_event=None):
    """Run the pipeline over the recording; returns (rows (k, 7): t, p, std; onset_t or None; last estimate).
    `on_estimate(est)` and `on_event(ev)` see each estimate and pipeline event as it comes.

    Rows come at the estimator's output cadence, never more than rate_hz per second. The
    recording is fed in chunks of chunk_s with the proprioception stamped up to each chunk's
    end; every estimate still uses only samples (and proprioception) stamped at or before it.
    """
    pipeline.params.output_period_s = max(1.0 / rate_hz, pipeline.params.output_period_s)
    t, p, std = [], [], []
    last: ContactEstimate | None = None
    onset_t = None
    for batch in fed_chunks(rec, pipeline, chunk_s):
        events, estimates = pipeline.process_all(batch)
        for ev in events:
            if ev["kind"] == "contact_onset" and onset_t is None:
                onset_t = ev["t"]
            if on_event is not None:
                on_event(ev)
        for est in estimates:
            last = est
            if on_estimate is not None:
                on_estimate(est)
            t.append(est.t)
            p.append(est.p)
            std.append(est.std)
    # the rows stacked once (one concatenate per estimate was a tenth of a replay's time)
    return (np.column_stack([t, p, std]) if t else np.zeros((0, 7))), onset_t, last


def fed_chunks(rec: Recording, pipeline: ContactPipeline, chunk_s: float):
    """The recording's IMU samples as (n, 7) batches of chunk_s, each yielded once the pipeline has
    been handed the proprioception stamped up to its end (the TCP's own rate is derived from the
    orientations by the pipeline: recordings carry none)."""
    R = quat_to_matrix(rec.tcp_quat)
    vel, force = rec.tcp_vel, rec.grip_force
    batch = np.column_stack([rec.imu_t, rec.gyro, rec.accel])
    grid = np.arange(rec.imu_t[0] + chunk_s, rec.imu_t[-1] + chunk_s, chunk_s)
    ends = np.unique(np.append(np.searchsorted(rec.imu_t, grid, side="right"), len(rec.imu_t)))
    j, start = 0, 0        # the next proprioception sample to hand over; the next IMU sample
    for end in ends:
        if end <= start:
            continue
        t_end = rec.imu_t[end - 1]
        while j < len(rec.tcp_t) and rec.tcp_t[j] <= t_end:
            pipeline.add_proprio(rec.tcp_t[j], rec.tcp_pos[j], None if vel is None else vel[j], R[j], None,
                                 np.nan if force is None else force[j])
            j += 1
        yield batch[start:end]
        start = end


def replay_onsets(rec: Recording, pipeline: ContactPipeline, episode_s: float = 0.3, chunk_s: float = 0.02) -> list:
    """Every contact_onset event of a causal replay, each episode released `episode_s` after its
    detection (as a task's end releases it; the trigger then settles and re-arms as the daemon's
    does): how often the trigger fires over a whole recording, not only its first onset."""
    found, release_at = [], None
    for batch in fed_chunks(rec, pipeline, chunk_s):
        if release_at is not None and batch[-1, 0] >= release_at:
            pipeline.release()
            release_at = None
        events, _ = pipeline.process_all(batch)
        for ev in events:
            if ev["kind"] == "contact_onset":
                found.append(ev)
                release_at = ev["detected_t"] + episode_s
    return found


def replay_live(rec: Recording, live: LiveLog, pipeline: ContactPipeline, on_estimate=None):
    """Run the pipeline over a daemon recording as the live estimator ran: the same passes (each
    pass's IMU batch), each proprioception sample added before the pass it reached live, the
    directives, data rates and clipping points as they changed, from the gyro bias the live
    pipeline had at the start. Returns (rows (k, 7): t, p, std, one per estimate the live pass
    published; onset_t or None; last estimate). `pipeline` must be built from the daemon's
    estimator config: then its answer is the live one (docs/recordings.md states the tolerance)."""
    from tecdard.control.pipeline import EstimatorDirective
    R = quat_to_matrix(rec.tcp_quat)
    force = rec.grip_force
    batch = np.column_stack([rec.imu_t, rec.gyro, rec.accel])
    pipeline.cond.set_bias_state(live.bias0)
    changes = {c["pass"]: c for c in live.changes}
    applied = None
    rows, last, onset_t = [], None, None
    j, start = 0, 0
    for k, end in enumerate(live.pass_end):
        while j < len(rec.tcp_t) and live.tcp_pass[j] <= k:
            pipeline.add_proprio(rec.tcp_t[j], rec.tcp_pos[j], None if rec.tcp_vel is None else rec.tcp_vel[j], R[j],
                                 live.tcp_w[j], np.nan if force is None else force[j])
            j += 1
        change = changes.get(k)
        if change is not None:
            directive = EstimatorDirective(**{f: change["directive"][f] for f in DIRECTIVE_FIELDS
                                              if f in change["directive"]})
            if applied is None:          # the state the live pipeline was in: settings, not a release
                pipeline.set_trigger_armed(directive.armed)
                pipeline.set_arc_following(directive.arc_following)
                pipeline.hold_bias(directive.bias_held)
            else:
                pipeline.follow(directive, applied)
            applied = directive
            if change.get("odr_hz"):
                pipeline.set_odr(float(change["odr_hz"]))
            if change.get("saturation"):
                pipeline.set_saturation(*map(float, change["saturation"]))
        events, est = pipeline.process(batch[start:end])
        start = end
        for ev in events:
            if ev["kind"] == "contact_onset" and onset_t is None:
                onset_t = ev["t"]
        if est is not None:
            last = est
            rows.append(np.concatenate([[est.t], est.p, est.std]))
            if on_estimate is not None:
                on_estimate(est)
    return (np.array(rows) if rows else np.zeros((0, 7))), onset_t, last


def write_csv(out, rows: np.ndarray) -> None:
    """The rows as `t,px,py,pz,sx,sy,sz` to a path or an open text file."""
    if isinstance(out, (str, bytes)) or hasattr(out, "__fspath__"):
        with open(out, "w") as f:
            write_csv(f, rows)
        return
    out.write("t,px,py,pz,sx,sy,sz\n")
    for r in rows:
        out.write(f"{r[0]:.9f},{r[1]:.6f},{r[2]:.6f},{r[3]:.6f},{r[4]:.6f},{r[5]:.6f},{r[6]:.6f}\n")


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
    from tecdard.tools.args import add_replay_options
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
    from tecdard.tools.args import BadInput, estimates, recording_and_pipeline, refused, show_path_error

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
