"""Recordings `tecdar-recording/1` (.npz): strict reading with one-line errors naming the key, and writing."""
from __future__ import annotations

import json
import pathlib
import zipfile
from dataclasses import dataclass, field

import numpy as np

FORMAT = "tecdar-recording/1"
QUAT_NORM_TOL = 1e-3
UNIT_TOL = 1e-3


class RecordingError(ValueError):
    """A malformed recording; the message is one line and names the key."""


@dataclass
class Recording:
    imu_t: np.ndarray            # (N,) s
    gyro: np.ndarray             # (N, 3) rad/s, IMU frame, raw
    accel: np.ndarray            # (N, 3) m/s^2, IMU frame, gravity included
    tcp_t: np.ndarray            # (M,) s
    tcp_pos: np.ndarray          # (M, 3) m, world
    tcp_quat: np.ndarray         # (M, 4) (x, y, z, w), world <- TCP
    imu_in_tcp_quat: np.ndarray  # (4,) (x, y, z, w), TCP <- IMU
    grip_force: np.ndarray | None = None    # (M,) N
    plane_normal: np.ndarray | None = None  # (3,) world unit
    tcp_vel: np.ndarray | None = None       # (M, 3) m/s, world
    meta: dict = field(default_factory=dict)

    @classmethod
    def from_fields(cls, fields: dict) -> "Recording":
        """From a dict of the format's keys (e.g. robots.scenarios.generate); absent optionals are None."""
        return cls(**{k: fields[k] for k in ("imu_t", "gyro", "accel", "tcp_t", "tcp_pos", "tcp_quat",
                                             "imu_in_tcp_quat")},
                   grip_force=fields.get("grip_force"), plane_normal=fields.get("plane_normal"),
                   tcp_vel=fields.get("tcp_vel"), meta=fields.get("meta") or {})

    @property
    def imu_rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.imu_t)))

    @property
    def tcp_rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.tcp_t)))

    @property
    def duration_s(self) -> float:
        return float(self.imu_t[-1] - self.imu_t[0])


def _raw(data, key: str, required: bool, expected: str):
    """The stored array for key, None when optional and absent; RecordingError otherwise."""
    if key not in data:
        if required:
            raise RecordingError(f"{key}: missing required key")
        return None
    try:
        return data[key]
    except ValueError:
        raise RecordingError(f"{key}: holds Python objects (pickled); expected {expected}") from None


def _array(data, key: str, shape: tuple, required: bool = True):
    """The key as float64 of `shape` (None entries: any length); RecordingError otherwise."""
    raw = _raw(data, key, required, "a numeric array")
    if raw is None:
        return None
    if raw.dtype.kind not in "fiu":
        raise RecordingError(f"{key}: expected a numeric array, got dtype {raw.dtype}")
    arr = np.asarray(raw, dtype=np.float64)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise RecordingError(f"{key}: expected shape {want}, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        row = int(np.argwhere(bad)[0][0]) if arr.ndim else 0
        raise RecordingError(f"{key}: contains NaN or inf (first at row {row})")
    return arr


def _string(data, key: str, required: bool) -> str | None:
    raw = _raw(data, key, required, "a string")
    if raw is None:
        return None
    if raw.ndim != 0 or raw.dtype.kind not in "US":
        raise RecordingError(f"{key}: expected a string scalar, got dtype {raw.dtype} shape {raw.shape}")
    value = raw.item()
    return value.decode() if isinstance(value, bytes) else str(value)


def _increasing(t: np.ndarray, key: str) -> None:
    if len(t) < 2:
        raise RecordingError(f"{key}: needs at least 2 samples, got {len(t)}")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0)) + 1
        raise RecordingError(f"{key}: timestamps must be strictly increasing (row {i}: {t[i]!r} after {t[i - 1]!r})")


def _same_length(arr: np.ndarray, key: str, n: int, of: str) -> None:
    if len(arr) != n:
        raise RecordingError(f"{key}: has {len(arr)} rows but {of} has {n}")


def _unit_quats(q: np.ndarray, key: str) -> np.ndarray:
    norms = np.linalg.norm(np.atleast_2d(q), axis=1)
    bad = np.abs(norms - 1.0) > QUAT_NORM_TOL
    if bad.any():
        i = int(np.argmax(bad))
        where = f"row {i} " if q.ndim == 2 else ""
        raise RecordingError(f"{key}: {where}is not a unit quaternion (|q| = {norms[i]:.6f})")
    return q / (norms[:, None] if q.ndim == 2 else norms[0])


def load_recording(path: str | pathlib.Path) -> Recording:
    """Read and validate a recording; every problem is a RecordingError naming the key."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise RecordingError(f"{path}: not a NumPy .npz file ({type(exc).__name__})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise RecordingError(f"{path}: a single .npy array, expected a .npz archive")
    with npz as data:
        keys = {k for k in data.files if not k.startswith("truth_")}
        get = _Lazy(data, keys)
        fmt = _string(get, "format", True)
        if fmt != FORMAT:
            raise RecordingError(f"format: expected {FORMAT!r}, got {fmt!r}")
        imu_t = _array(get, "imu_t", (None,))
        _increasing(imu_t, "imu_t")
        n = len(imu_t)
        gyro = _array(get, "gyro", (None, 3))
        _same_length(gyro, "gyro", n, "imu_t")
        accel = _array(get, "accel", (None, 3))
        _same_length(accel, "accel", n, "imu_t")
        tcp_t = _array(get, "tcp_t", (None,))
        _increasing(tcp_t, "tcp_t")
        m = len(tcp_t)
        tcp_pos = _array(get, "tcp_pos", (None, 3))
        _same_length(tcp_pos, "tcp_pos", m, "tcp_t")
        tcp_quat = _array(get, "tcp_quat", (None, 4))
        _same_length(tcp_quat, "tcp_quat", m, "tcp_t")
        tcp_quat = _unit_quats(tcp_quat, "tcp_quat")
        mount = _unit_quats(_array(get, "imu_in_tcp_quat", (4,)), "imu_in_tcp_quat")
        grip = _array(get, "grip_force", (None,), required=False)
        if grip is not None:
            _same_length(grip, "grip_force", m, "tcp_t")
        tcp_vel = _array(get, "tcp_vel", (None, 3), required=False)
        if tcp_vel is not None:
            _same_length(tcp_vel, "tcp_vel", m, "tcp_t")
        normal = _array(get, "plane_normal", (3,), required=False)
        if normal is not None and abs(np.linalg.norm(normal) - 1.0) > UNIT_TOL:
            raise RecordingError(f"plane_normal: expected a unit vector, |n| = {np.linalg.norm(normal):.6f}")
        meta_s = _string(get, "meta", False)
        meta = {}
        if meta_s is not None:
            try:
                meta = json.loads(meta_s)
            except json.JSONDecodeError as exc:
                raise RecordingError(f"meta: not valid JSON ({exc.msg} at char {exc.pos})") from None
            if not isinstance(meta, dict):
                raise RecordingError(f"meta: expected a JSON object, got {type(meta).__name__}")
    return Recording(imu_t, gyro, accel, tcp_t, tcp_pos, tcp_quat, mount, grip,
                     None if normal is None else normal / np.linalg.norm(normal), tcp_vel, meta)


class _Lazy:
    """Mapping view of an NpzFile restricted to non-truth keys (loads arrays on access)."""

    def __init__(self, data, keys):
        self._data, self._keys = data, keys

    def __contains__(self, key):
        return key in self._keys

    def __getitem__(self, key):
        return self._data[key]


def load_truth(path: str | pathlib.Path) -> dict:
    """The `truth_*` keys of a simulated recording (benchmarks and tests only; estimators never see them)."""
    with np.load(path, allow_pickle=False) as data:
        return {k[len("truth_"):]: data[k] for k in data.files if k.startswith("truth_")}


def save_recording(path: str | pathlib.Path, rec: Recording, truth: dict | None = None) -> None:
    arrays = {
        "format": np.array(FORMAT), "imu_t": rec.imu_t, "gyro": rec.gyro, "accel": rec.accel,
        "tcp_t": rec.tcp_t, "tcp_pos": rec.tcp_pos, "tcp_quat": rec.tcp_quat,
        "imu_in_tcp_quat": rec.imu_in_tcp_quat,
    }
    if rec.grip_force is not None:
        arrays["grip_force"] = rec.grip_force
    if rec.plane_normal is not None:
        arrays["plane_normal"] = rec.plane_normal
    if rec.tcp_vel is not None:
        arrays["tcp_vel"] = rec.tcp_vel
    if rec.meta:
        arrays["meta"] = np.array(json.dumps(rec.meta))
    for k, v in (truth or {}).items():
        arrays[f"truth_{k}"] = np.asarray(v)
    np.savez_compressed(path, **arrays)
