"""A capture: the estimator thread's passes and the daemon's events that the recorder keeps, the records
that hand them to the recorder's thread, and how a capture becomes a tecdar-recording/1 file with its
live_* log (docs/recordings.md, "Daemon recordings")."""
from __future__ import annotations

import json
import pathlib
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from tecdard.control.geometry import matrix_to_quat
from tecdard.recording.format import Recording
from tecdard.safejson import json_ready


class EmptyCapture(ValueError):
    """A capture with too little in it to be a recording."""


@dataclass(frozen=True)
class CaptureCommand:
    """A capture on demand, from the main thread to the recorder's: start (arg: its label), stop (the
    label) or close (why: the daemon is stopping)."""
    what: str
    arg: str


@dataclass(frozen=True)
class Commanded:
    """A control tick's command, from the control thread to the recorder's: its time (s, monotonic) and the
    joint rates sent (rad/s; zeros where the arm was held)."""
    t: float
    qd: np.ndarray


@dataclass(frozen=True)
class NotedEvent:
    """A published event, from the main thread to the recorder's (a capture keeps its task's)."""
    event: dict


@dataclass
class Pass:
    """One pass of the estimator thread, as it fed its pipeline."""
    proprio: list                 # the control.proprio.ProprioSample records added before the batch
    directive: object             # the EstimatorDirective in force for the batch
    odr_hz: float | None
    saturation: tuple | None      # (gyro rad/s, accel m/s^2) clipping points in force
    batch: np.ndarray             # (n, 7) t, gyro, accel
    events: list                  # the pipeline's events of this pass
    estimate: object              # ContactEstimate or None
    bias: np.ndarray              # the conditioner's bias state before the batch (GyroConditioner.bias_state)

    @property
    def t_end(self) -> float | None:
        return float(self.batch[-1, 0]) if len(self.batch) else None


@dataclass
class Capture:
    reason: str                   # "episode" or "manual"
    label: str
    task: str | None
    verb: str | None
    episode: int
    passes: list
    events: list
    t_open: float = field(default_factory=time.monotonic)
    manual: bool = False
    lost_at_open: int = 0         # the recorder's dropped count when it opened (its own losses: the difference)
    end_by: float | None = None   # its episode has ended: written at its task's end, or at this time
    path: pathlib.Path | None = None      # where it is written (fixed at its first checkpoint)
    onset_t: float | None = None          # the contact onset it opened on (None: opened on a command)
    saved_at: float = field(default_factory=time.monotonic)   # its last checkpoint (or its opening)
    commands: list = field(default_factory=list)              # the control ticks' Commanded, in order


def build(cap: Capture, meta: dict) -> tuple[Recording, dict]:
    """The capture as a Recording and its `live_*` keys; EmptyCapture when it holds too little."""
    passes = cap.passes
    batches = [p.batch for p in passes if len(p.batch)]
    if not batches:
        raise EmptyCapture("no IMU samples")
    imu = np.concatenate(batches)
    rows = [(k, s) for k, p in enumerate(passes) for s in p.proprio]
    if len(imu) < 2 or len(rows) < 2:
        raise EmptyCapture(f"{len(imu)} IMU and {len(rows)} proprioception samples")
    tcp_t = np.array([s.t for _, s in rows])
    keep = np.concatenate([[True], np.diff(tcp_t) > 0])       # the format wants strictly increasing times
    rows = [r for r, k in zip(rows, keep) if k]
    tcp_t = tcp_t[keep]
    R = np.array([s.R_world_tcp for _, s in rows])
    vel = [s.v_world for _, s in rows]
    w = [s.w_world for _, s in rows]
    grip = np.array([s.grip_force_n for _, s in rows], dtype=float)
    first = passes[0]
    rec = Recording(
        imu_t=imu[:, 0].copy(), gyro=imu[:, 1:4].copy(), accel=imu[:, 4:7].copy(), tcp_t=tcp_t,
        tcp_pos=np.array([s.p_world for _, s in rows]), tcp_quat=np.array([matrix_to_quat(r) for r in R]),
        imu_in_tcp_quat=np.asarray(meta["imu_in_tcp_quat"], float),
        # where the gripper said no force (not holding yet, or a backend that reads none) the estimator took
        # the configured one: so does the file, and a replay takes what the live estimator took
        grip_force=np.where(np.isfinite(grip), grip, float(meta["grip_force"])) if np.any(np.isfinite(grip))
        else None,
        plane_normal=None if meta.get("plane_normal") is None else np.asarray(meta["plane_normal"], float),
        tcp_vel=np.array(vel) if all(v is not None for v in vel) else None,
        meta={k: v for k, v in meta.items() if k not in ("imu_in_tcp_quat", "plane_normal")} |
        # measured grip forces are the recording's own (the grip_force key); the configured one is assumed
        {"grip_force_assumed": bool(meta.get("grip_force_assumed")) and not np.all(np.isfinite(grip))} |
        # the stamps are the monotonic clock's: the wall clock's offset from it lines them up with a lab's data
        {"clock": {"stamps": "CLOCK_MONOTONIC, s", "wall_minus_monotonic_s": time.time() - time.monotonic()}} |
        {"task": cap.task, "verb": cap.verb, "label": cap.label, "reason": cap.reason})
    # each pass's batch end (into imu_t), and the pass at which each proprioception sample arrived
    ends = np.cumsum([len(p.batch) for p in passes])
    changes, last = [], (None, None, None)
    for k, p in enumerate(passes):
        d = asdict(p.directive)
        now = (d, p.odr_hz, None if p.saturation is None else list(p.saturation))
        if now != last:
            changes.append({"pass": k, "directive": d, "odr_hz": p.odr_hz, "saturation": now[2]})
            last = now
    ests = [p.estimate for p in passes if p.estimate is not None]
    events = [e for p in passes for e in p.events] + cap.events
    extra = {
        "live_pass_end": ends.astype(np.int64),
        "live_tcp_pass": np.array([k for k, _ in rows], dtype=np.int64),
        "live_tcp_w": np.array([np.zeros(3) if x is None else x for x in w], dtype=float),
        "live_changes": np.array(json.dumps(json_ready(changes))),
        "live_bias0": np.asarray(first.bias, float),
        "live_est": np.array([np.concatenate([[e.t], e.p, e.std]) for e in ests]).reshape(-1, 7),
        # the rotation axis with each estimate (NaN until the motion excites it)
        "live_axis": np.array([np.full(3, np.nan) if e.axis is None else e.axis for e in ests], float).reshape(-1, 3),
        "live_events": np.array(json.dumps(json_ready(events))),
    }
    q = [s.q for _, s in rows if s.q is not None]
    if len(q) == len(rows) and q and len({len(x) for x in q}) == 1 and np.all(np.isfinite(q)):
        extra["live_q"] = np.array(q, dtype=float)         # the measured joints, rad (the export draws the arm)
        qd = [s.qd for _, s in rows]
        if all(x is not None and len(x) == len(q[0]) for x in qd) and np.all(np.isfinite(qd)):
            extra["live_qd"] = np.array(qd, dtype=float)   # and their measured rates, rad/s
    gripper = np.array([[s.grip_width_m, s.grasped] for _, s in rows], dtype=float)
    if np.any(np.isfinite(gripper)):                      # the gripper's opening (m) and whether it held; -1: unknown
        extra["live_gripper"] = np.where(np.isfinite(gripper), gripper, -1.0)
    cmd = np.array([[c.t, *c.qd] for c in cap.commands                  # each tick's action: t, then the
                    if imu[0, 0] <= c.t <= imu[-1, 0] and len(c.qd) == len(cap.commands[-1].qd)], dtype=float)
    if len(cmd) and np.all(np.isfinite(cmd)):                           # commanded joint rates
        extra["live_cmd"] = cmd
    wrench = [s.wrench for _, s in rows]
    if any(w is not None for w in wrench):                # the arm's own estimate at the TCP; nan where it gave none
        extra["tcp_wrench"] = np.array([np.full(6, np.nan) if w is None else w for w in wrench], dtype=float)
        rec.meta["wrench_source"] = next(s.wrench_source for _, s in reversed(rows) if s.wrench is not None)
    return rec, extra
