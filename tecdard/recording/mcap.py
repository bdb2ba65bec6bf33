"""A recording, with the estimate replayed over it (tecdard.recording.replay), as an MCAP file for Foxglove
(tecdard/recording/foxglove.py's topics): the library under `tecdard export` and the fleet's episode
store. `.npz` stays the analysis format; MCAP is for looking."""
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


def write_mcap(out: str, rec, estimates: list, events: list, truth: dict, q: np.ndarray | None = None,
               gripper: np.ndarray | None = None, wrench: np.ndarray | None = None) -> int:
    """Write the recording, its estimates (ContactEstimate), events and (a daemon recording's) joints,
    gripper (`live_gripper`: opening and grasped, -1 unknown) and the arm's wrench (`tcp_wrench`) to `out`;
    the messages written."""
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
    if gripper is not None:
        for j in range(len(rec.tcp_t)):
            items.append((rec.tcp_t[j], 5, "gripper", j))
    if wrench is not None:
        for j in range(len(rec.tcp_t)):
            if np.all(np.isfinite(wrench[j, :3])):
                items.append((rec.tcp_t[j], 6, "wrench", j))
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
            elif kind == "gripper":
                width, held = gripper[x]
                force = None if rec.grip_force is None or held != 1 else float(rec.grip_force[x])
                ch.gripper(t, None if width < 0 else float(width), force, None if held < 0 else bool(held))
            elif kind == "wrench":
                ch.wrench(t, wrench[x], str(meta.get("wrench_source") or ""))
            else:
                ch.event(t, x)
    finally:
        ch.close()
        try:
            writer.close()
        except Exception as exc:            # foxglove's FoxgloveError (a RuntimeError): a write failed
            raise ExportError(f"--mcap: writing failed ({first_line(exc, 200)})") from None
    return len(items)


def export_mcap(path, out, config: str | None = None, method: str | None = None,
                ignore_live: bool = False) -> tuple[int, list, list]:
    """Replay the recording at `path` (the estimator tuned by the YAML file `config`: the daemon's own
    makes the replay the live answer) and write it as MCAP to `out`: (messages, estimates, events).
    ReplayError, ExportError or RecordingError (one line) otherwise."""
    from tecdard.recording.format import load_truth
    from tecdard.recording.replay import open_replay, run_replay
    found, events = [], []
    r = open_replay(path, config, method, ignore_live)
    run_replay(r, on_estimate=found.append, on_event=events.append)
    if r.live is not None:
        events = r.live.events          # the pipeline's and the daemon's, as they happened live
    live = r.live
    n = write_mcap(str(out), r.rec, found, events, load_truth(path), None if live is None else live.q,
                   None if live is None else live.gripper, None if live is None else live.wrench)
    return n, found, events
