"""`tecdard export REC.npz --mcap OUT.mcap`: a recording, with the estimate replayed over it, as an MCAP
file for Foxglove (tecdard/recording/foxglove.py's topics). `.npz` stays the analysis format; MCAP is for looking."""
from __future__ import annotations

import numpy as np

from tecdard.control.geometry import quat_to_matrix
from tecdard.safejson import first_line

IMU_BATCH_S = 0.01             # the IMU in messages of this much


class ExportError(Exception):
    """What keeps an export from being written, in one line."""


def wall_clock_offset(meta: dict) -> float | None:
    """A daemon recording's wall clock minus its monotonic stamps (s), or None where it has none."""
    clock = (meta or {}).get("clock")
    off = clock.get("wall_minus_monotonic_s") if isinstance(clock, dict) else None
    if isinstance(off, (int, float)) and not isinstance(off, bool) and np.isfinite(off) and 0 < off < 1e11:
        return float(off)
    return None


def write_mcap(out: str, rec, estimates: list, events: list, truth: dict, q: np.ndarray | None = None) -> int:
    """Write the recording, its estimates (ContactEstimate), events and (a daemon recording's) joints to
    `out`; the messages written."""
    try:
        import foxglove

        from tecdard.recording.foxglove import Channels, robot_description
    except ImportError:
        raise ExportError("needs foxglove-sdk: pip install 'tecdar[viz]'") from None
    items = []                  # (t, order, kind, payload): written in time order
    edges = np.searchsorted(rec.imu_t, np.arange(rec.imu_t[0], rec.imu_t[-1] + IMU_BATCH_S, IMU_BATCH_S), "right")
    edges = np.unique(np.append(edges, len(rec.imu_t)))
    start = 0
    for end in edges:
        if end > start:
            items.append((rec.imu_t[end - 1], 0, "imu", (start, end)))
            start = end
    R = quat_to_matrix(rec.tcp_quat)
    for j in range(len(rec.tcp_t)):
        items.append((rec.tcp_t[j], 1, "tcp", j))
    desc = None
    model = (rec.meta or {}).get("model")
    if q is not None and isinstance(model, str):
        try:
            desc = robot_description(model)
        except Exception:                   # an arm we have no URDF for: the joints still go out
            desc = None
        if desc is not None and len(desc.joint_names) != q.shape[1]:
            raise ExportError(f"live_q: {q.shape[1]} joints, but meta.model {model} has {len(desc.joint_names)}")
        for j in range(len(rec.tcp_t)):
            items.append((rec.tcp_t[j], 4, "joints", j))
    for est in estimates:
        items.append((est.t, 2, "contact", est))
    for ev in events:
        t = ev.get("t")
        if isinstance(t, (int, float)) and np.isfinite(t):
            items.append((float(t), 3, "event", ev))
    items.sort(key=lambda x: (x[0], x[1]))
    R_mount = quat_to_matrix(rec.imu_in_tcp_quat)
    ctx = foxglove.Context()
    try:
        writer = foxglove.open_mcap(out, allow_overwrite=True, context=ctx)
    except Exception as exc:
        raise ExportError(f"--mcap: cannot write {out} ({first_line(exc, 200)})") from None
    offset = wall_clock_offset(rec.meta)
    if offset is not None:          # a daemon's recording: its monotonic stamps moved to wall-clock time
        ch = Channels(ctx, origin_s=0.0, epoch_s=offset)
        clock = {"log_time": "wall clock (UTC, ns since the Unix epoch)", "wall_minus_monotonic_s": repr(offset)}
    else:                           # a recording with a clock of its own: its first sample at the epoch
        first = min(rec.imu_t[0], rec.tcp_t[0])
        ch = Channels(ctx, origin_s=first)
        clock = {"log_time": "the recording's own clock, its first sample at the Unix epoch (no wall clock in it)",
                 "first_sample_s": repr(float(first))}
    meta = rec.meta or {}
    writer.write_metadata("tecdar", {**clock, **{k: str(meta[k]) for k in ("robot", "model", "backend", "task", "verb")
                                                  if meta.get(k) is not None}})
    names = desc.joint_names if desc is not None else [f"joint{i + 1}" for i in range(0 if q is None else q.shape[1])]
    try:
        if desc is not None:
            ch.robot(min(rec.imu_t[0], rec.tcp_t[0]), desc)
        p_true = truth.get("p_c")
        if np.shape(p_true) == (3,) and np.all(np.isfinite(p_true)):
            axis = truth.get("axis") if np.shape(truth.get("axis")) == (3,) else None
            ch.contact(rec.imu_t[0], np.asarray(p_true, float), np.eye(3) * 1e-6, axis, entity="truth",
                       rgba=(0.1, 0.7, 0.2, 0.8))
        for t, _, kind, x in items:
            if kind == "imu":
                a, b = x
                ch.imu_batch(rec.imu_t[a:b], rec.gyro[a:b], rec.accel[a:b])
            elif kind == "tcp":
                ch.tcp(t, rec.tcp_pos[x], R[x], R_mount)
            elif kind == "contact":
                ch.contact(t, x.p, x.cov, x.axis)
            elif kind == "joints":
                ch.joint_states(t, names, q[x])
            else:
                ch.event(t, x)
    finally:
        ch.close()
        try:
            writer.close()
        except Exception as exc:            # foxglove's FoxgloveError (a RuntimeError): a write failed
            raise ExportError(f"--mcap: writing failed ({first_line(exc, 200)})") from None
    return len(items)


def add_parser(sub) -> None:
    from tecdard.tools.args import add_replay_options
    p = sub.add_parser("export", help="write a recording and its replayed estimate as MCAP for Foxglove")
    add_replay_options(p)
    p.add_argument("--mcap", required=True, help="OUT.mcap (replaced if it exists)")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard export`: exit 0, or 2 with one line."""
    from tecdard.files import OutputError, check_output, replacing
    from tecdard.recording.format import RecordingError
    from tecdard.tools.args import BadInput, refused, show_path_error

    try:
        check_output(args.mcap, "--mcap", [args.recording])       # never over the input, and before the replay
        with replacing(args.mcap, "--mcap") as tmp:     # a failed write leaves what was there
            n, found, events = _export(args, tmp)
    except (BadInput, ExportError, RecordingError) as exc:
        return refused("export", str(exc))
    except OutputError as exc:
        return refused("export", show_path_error(exc))
    print(f"{args.mcap}: {n} messages ({len(found)} estimates, {len(events)} events)")
    return 0


def _export(args, out) -> tuple[int, list, list]:
    """Replay args.recording and write the MCAP to `out`: (messages, estimates, events)."""
    from tecdard.recording.format import load_truth
    from tecdard.tools.args import estimates, recording_and_pipeline
    found, events = [], []
    rec, live, pipeline = recording_and_pipeline(args)
    estimates(args, rec, live, pipeline, on_estimate=found.append, on_event=events.append)
    if live is not None:
        events = live.events          # the pipeline's and the daemon's, as they happened live
    n = write_mcap(str(out), rec, found, events, load_truth(args.recording), None if live is None else live.q)
    return n, found, events


def mcap_of(recording, out, config: str | None = None) -> int:
    """A recording as `tecdard export` writes it (the episode store's MCAP), the estimator tuned by
    `config` (the daemon's own, so that the replay is the live answer): the messages written; BadInput,
    ExportError or RecordingError (one line) otherwise."""
    import argparse
    args = argparse.Namespace(recording=str(recording), mcap=str(out), method=None, config=config, ignore_live=False)
    return _export(args, out)[0]
