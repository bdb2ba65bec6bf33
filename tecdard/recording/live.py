"""A daemon recording's `live_*` members (docs/recordings.md, "Daemon recordings"): how its live estimator
was fed, so that a replay is the live answer, and what the arm did besides (its joints, gripper, wrench and the
control ticks' commands). Read as strictly as the core members (recording/format.py), with one-line errors
naming the key."""
from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass

import numpy as np

from tecdard.recording.format import MAX_DURATION_S, Recording, RecordingError, _array, _Npz, _string, _why
from tecdard.recording.members import MEMBERS
from tecdard.safejson import JsonLimitError, loads, show

MAX_JOINTS = 12                  # live_q, live_cmd: the joints of one arm
MAX_JOINT_RAD = 100.0            # live_q: no revolute joint turns further (a corrupt file beyond)
MAX_JOINT_RATE = 100.0           # live_qd, live_cmd: rad/s no arm turns (a UR's fastest joint: 3.14 rad/s)
MAX_EVENTS = 100_000             # live_events: a 120 s capture holds hundreds


def _member(data: _Npz, key: str, n_tcp: int, n: int | None, nan_ok: bool = False):
    """A declared live member as float64, its proprioception rows n_tcp and its joints n."""
    m = MEMBERS[key]
    joints = {"n": n, "1+n": None if n is None else 1 + n}
    shape = tuple(s if isinstance(s, int) else n_tcp if s == "M" else joints.get(s) for s in m.shape)
    return _array(data, key, shape, rows_max=m.rows_max, nan_ok=nan_ok)


def _commands(data: _Npz, rec: Recording, n: int | None) -> np.ndarray | None:
    """live_cmd: (T, 1 + n) rows of a tick's time, strictly increasing and within the recording's span, and
    the joint rates it commanded (as many joints as live_q's where that is given)."""
    if "live_cmd" not in data:
        return None
    declared = data.header("live_cmd")[1]
    if len(declared) != 2 or not 2 <= declared[1] <= MAX_JOINTS + 1 or (n is not None and declared[1] != n + 1):
        joints = f"{n}" if n is not None else f"1..{MAX_JOINTS}"
        raise RecordingError(f"live_cmd: expected shape (T, 1 + {joints} joints), got {declared}")
    cmd = _member(data, "live_cmd", len(rec.tcp_t), declared[1] - 1)
    t = cmd[:, 0]
    lo, hi = min(rec.imu_t[0], rec.tcp_t[0]) - 1.0, max(rec.imu_t[-1], rec.tcp_t[-1]) + 1.0
    if len(t) and (np.any(np.diff(t) <= 0) or t[0] < lo or t[-1] > hi):
        raise RecordingError(f"live_cmd: tick times must increase strictly within the recording "
                             f"({rec.imu_t[0]:.3f} to {rec.imu_t[-1]:.3f} s)")
    if np.any(np.abs(cmd[:, 1:]) > MAX_JOINT_RATE):
        raise RecordingError(f"live_cmd: joint rates beyond {MAX_JOINT_RATE:g} rad/s")
    return cmd


@dataclass
class LiveLog:
    """A daemon recording's `live_*` keys: how the live estimator was fed (docs/recordings.md)."""
    pass_end: np.ndarray         # (B,) int: imu rows fed up to each estimator pass
    tcp_pass: np.ndarray         # (M,) int: the pass before which each proprioception sample was added
    tcp_w: np.ndarray            # (M, 3) the TCP's rate as reported, rad/s, world
    changes: list                # [{"pass", "directive", "odr_hz", "saturation"}] where they changed
    bias0: np.ndarray            # (4,) the gyro bias at the first pass (rad/s, IMU frame) and its rest time (s)
    est: np.ndarray              # (K, 7) the live estimates: t, p, std
    events: list
    axis: np.ndarray | None = None      # (K, 3) the rotation axis with each estimate, world unit; nan until excited
    q: np.ndarray | None = None  # (M, n) the measured joints at each proprioception sample, rad (newer recordings)
    qd: np.ndarray | None = None        # (M, n) the joints' measured rates, rad/s (with q)
    gripper: np.ndarray | None = None   # (M, 2) the gripper's opening (m) and whether it held (1, 0; -1: unknown)
    wrench: np.ndarray | None = None    # (M, 6) the arm's own wrench at the TCP: force N, torque N m, world; nan: none
    cmd: np.ndarray | None = None       # (T, 1 + n) each control tick's time (s) and commanded joint rates (rad/s)


def load_live(path: str | pathlib.Path, rec: Recording) -> LiveLog | None:
    """The live_* keys of a daemon recording checked against `rec`, None when there are none;
    RecordingError naming the key when they are malformed."""
    data = _Npz(pathlib.Path(path))
    try:
        if "live_pass_end" not in data:
            return None
        n_imu, n_tcp = len(rec.imu_t), len(rec.tcp_t)

        def array(key: str, n: int | None = None, nan_ok: bool = False):
            """A declared live member, its proprioception rows n_tcp and its joints n."""
            return _member(data, key, n_tcp, n, nan_ok)

        ends = array("live_pass_end")
        if len(ends) == 0 or np.any(np.diff(ends) < 0) or ends[0] < 0 or ends[-1] != n_imu:
            raise RecordingError(f"live_pass_end: expected non-decreasing row counts ending at {n_imu}")
        passes = array("live_tcp_pass")
        if np.any(np.diff(passes) < 0) or (n_tcp and (passes[0] < 0 or passes[-1] >= len(ends))):
            raise RecordingError(f"live_tcp_pass: expected non-decreasing pass numbers below {len(ends)}")
        changes = _json_list(data, "live_changes")
        for c in changes:
            if not isinstance(c, dict) or not isinstance(c.get("pass"), int) or not isinstance(c.get("directive"), dict):
                raise RecordingError("live_changes: expected [{\"pass\": int, \"directive\": {...}, ...}]")
        q = None
        if "live_q" in data:
            declared = data.header("live_q")[1]
            if len(declared) != 2 or not 1 <= declared[1] <= MAX_JOINTS:     # refused before it is read
                raise RecordingError(f"live_q: expected shape ({n_tcp}, 1..{MAX_JOINTS}), got {declared}")
            q = array("live_q", declared[1])
            if np.any(np.abs(q) > MAX_JOINT_RAD):
                raise RecordingError(f"live_q: expected ({n_tcp}, 1..{MAX_JOINTS}) joint angles within "
                                     f"{MAX_JOINT_RAD:g} rad")
        qd = None
        if "live_qd" in data:
            if q is None:
                raise RecordingError("live_qd: the joints' rates without live_q, their joints")
            qd = array("live_qd", q.shape[1])
            if np.any(np.abs(qd) > MAX_JOINT_RATE):
                raise RecordingError(f"live_qd: joint rates beyond {MAX_JOINT_RATE:g} rad/s")
        gripper = array("live_gripper") if "live_gripper" in data else None
        if gripper is not None and not (np.all((gripper[:, 0] == -1) | ((gripper[:, 0] >= 0) & (gripper[:, 0] <= 1)))
                                        and np.all(np.isin(gripper[:, 1], (-1.0, 0.0, 1.0)))):
            raise RecordingError(f"live_gripper: expected ({n_tcp}, 2) rows: an opening in 0..1 m (or -1), and 0, 1 or -1")
        # the arm's wrench: NaN where it gave none (a simulator's torque)
        wrench = array("tcp_wrench", nan_ok=True) if "tcp_wrench" in data else None
        est = array("live_est")
        axis = None
        if "live_axis" in data:
            axis = _array(data, "live_axis", (len(est), 3), nan_ok=True)
            norm = np.linalg.norm(axis, axis=1)
            if np.any(np.isfinite(norm) & (np.abs(norm - 1.0) > 1e-3)):
                raise RecordingError(f"live_axis: expected ({len(est)}, 3) unit vectors (or NaN)")
        return LiveLog(ends.astype(np.int64), passes.astype(np.int64), array("live_tcp_w"), changes,
                       array("live_bias0"), est, _events(data, rec), axis, q, qd, gripper, wrench,
                       _commands(data, rec, None if q is None else q.shape[1]))
    finally:
        data.close()


def _events(data: _Npz, rec: Recording) -> list:
    """live_events checked as strictly as the arrays: at most MAX_EVENTS, each a JSON object with a
    string `kind` and a finite `t` within MAX_DURATION_S of the recording's samples."""
    events = _json_list(data, "live_events")
    if len(events) > MAX_EVENTS:
        raise RecordingError(f"live_events: {len(events)} events, at most {MAX_EVENTS}")
    lo = min(rec.imu_t[0], rec.tcp_t[0]) - MAX_DURATION_S
    hi = max(rec.imu_t[-1], rec.tcp_t[-1]) + MAX_DURATION_S
    for i, ev in enumerate(events):
        if not isinstance(ev, dict):
            raise RecordingError(f"live_events[{i}]: expected a JSON object, got {show(ev)}")
        if not isinstance(ev.get("kind"), str):
            raise RecordingError(f"live_events[{i}].kind: expected a string, got {show(ev.get('kind'))}")
        t = ev.get("t")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or not lo <= t <= hi:
            raise RecordingError(f"live_events[{i}].t: {show(t)} is no time within {MAX_DURATION_S:g} s of the "
                                 f"recording ({rec.imu_t[0]:.3f} to {rec.imu_t[-1]:.3f} s)")
    return events


def _json_list(data: _Npz, key: str) -> list:
    text = _string(data, key, True)
    try:
        value = loads(text)
    except (JsonLimitError, ValueError) as exc:
        raise RecordingError(f"{key}: not JSON ({_why(exc)})") from None
    if not isinstance(value, list):
        raise RecordingError(f"{key}: expected a JSON list")
    return value
