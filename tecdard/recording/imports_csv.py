"""CSV logs for `tecdard import --csv MAP.yaml`: the YAML names each file's columns and units.

    imu:
      file: imu.csv                                   # relative to MAP.yaml's folder
      time: {column: t, unit: s}                      # s | ms | us | ns
      gyro: {columns: [gx, gy, gz], unit: rad/s}      # rad/s | deg/s
      accel: {columns: [ax, ay, az], unit: m/s^2}     # m/s^2 | g
    tcp:
      file: tcp.csv                                   # may be the IMU's file
      time: {column: t, unit: s}
      position: {columns: [x, y, z], unit: m}         # m | mm
      orientation: {columns: [qx, qy, qz, qw], convention: xyzw}   # xyzw | wxyz | rpy_deg | rpy_rad
      velocity: {columns: [vx, vy, vz], unit: m/s}    # optional: m/s | mm/s

Every file has a header row naming its columns. A row that is short, long, or holds anything but a
finite number in a column the map names is refused with the file, the row (1 = the header) and the
column; nothing is imported then.
"""
from __future__ import annotations

import csv
import math
import pathlib

import numpy as np

from tecdard.control.geometry import matrix_to_quat, rotvec_to_matrix
from tecdard.recording.imports import MAX_ROWS, ImportFailure, Streams

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
UNITS = {"gyro": {"rad/s": 1.0, "deg/s": math.pi / 180.0}, "accel": {"m/s^2": 1.0, "g": 9.80665},
         "position": {"m": 1.0, "mm": 1e-3}, "velocity": {"m/s": 1.0, "mm/s": 1e-3}}
CONVENTIONS = {"xyzw": 4, "wxyz": 4, "rpy_deg": 3, "rpy_rad": 3}
MAX_FIELD_CHARS = 64


def _section(doc: dict, name: str, required: bool = True) -> dict | None:
    sec = doc.get(name)
    if sec is None and not required:
        return None
    if not isinstance(sec, dict):
        raise ImportFailure(f"{name}: expected a mapping with file, time and columns")
    return sec


def _columns(sec: dict, where: str, key: str, n: int) -> list[str]:
    spec = sec.get(key)
    cols = spec.get("columns") if isinstance(spec, dict) else None
    if not isinstance(cols, list) or len(cols) != n or not all(isinstance(c, str) and c for c in cols):
        raise ImportFailure(f"{where}.{key}.columns: expected {n} column names")
    return cols


def _unit(sec: dict, where: str, key: str, table: dict) -> float:
    unit = (sec.get(key) or {}).get("unit", next(iter(table)))
    if unit not in table:
        raise ImportFailure(f"{where}.{key}.unit: expected one of {', '.join(table)}, got {str(unit)[:32]!r}")
    return table[unit]


def _read(path: pathlib.Path, wanted: list[str]) -> np.ndarray:
    """The named columns of a CSV file as floats (rows, len(wanted)); ImportFailure naming the row and column."""
    if not path.is_file():
        raise ImportFailure(f"{path}: no such file")
    rows = []
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ImportFailure(f"{path}: empty, expected a header row")
        header = [h.strip() for h in header]
        missing = [c for c in wanted if c not in header]
        if missing:
            raise ImportFailure(f"{path}: no column {missing[0]!r} (its columns: {', '.join(header[:12])[:200]})")
        idx = [header.index(c) for c in wanted]
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not x.strip() for x in row):
                continue
            if len(row) != len(header):
                raise ImportFailure(f"{path}: row {lineno} has {len(row)} fields, the header {len(header)}")
            vals = []
            for c, i in zip(wanted, idx):
                text = row[i].strip()
                try:
                    v = float(text) if len(text) <= MAX_FIELD_CHARS else math.nan
                except ValueError:
                    v = math.nan
                if not math.isfinite(v):
                    raise ImportFailure(f"{path}: row {lineno}, column {c!r}: {text[:32]!r} is not a finite number")
                vals.append(v)
            rows.append(vals)
            if len(rows) > MAX_ROWS:
                raise ImportFailure(f"{path}: more than {MAX_ROWS} rows")
    if not rows:
        raise ImportFailure(f"{path}: no rows after the header")
    return np.array(rows)


def _increasing(t: np.ndarray, path: pathlib.Path) -> None:
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise ImportFailure(f"{path}: row {i + 3}: time {t[i + 1]:.9g} s does not follow {t[i]:.9g} s")


def read_csv(map_path) -> Streams:
    """The streams a CSV map names (module doc)."""
    import yaml
    map_path = pathlib.Path(map_path)
    try:
        doc = yaml.safe_load(map_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ImportFailure(f"{map_path}: not a readable YAML map ({str(exc).splitlines()[0][:120]})") from None
    if not isinstance(doc, dict):
        raise ImportFailure(f"{map_path}: expected a mapping with imu and tcp")
    base = map_path.parent
    imu, tcp = _section(doc, "imu") or {}, _section(doc, "tcp") or {}
    imu_file, tcp_file = (base / str(sec.get("file", "")) for sec in (imu, tcp))
    t_col: dict[str, str] = {}
    for name, sec in (("imu", imu), ("tcp", tcp)):
        col = (sec.get("time") or {}).get("column")
        if not isinstance(col, str) or not col:
            raise ImportFailure(f"{name}.time.column: expected a column name")
        t_col[name] = col
    a = _read(imu_file, [t_col["imu"], *_columns(imu, "imu", "gyro", 3), *_columns(imu, "imu", "accel", 3)])
    t_imu = a[:, 0] * _unit(imu, "imu", "time", TIME_UNITS)
    _increasing(t_imu, imu_file)
    conv = (tcp.get("orientation") or {}).get("convention", "xyzw")
    if conv not in CONVENTIONS:
        raise ImportFailure(f"tcp.orientation.convention: expected one of {', '.join(CONVENTIONS)}, got {str(conv)[:32]!r}")
    vel_cols = _columns(tcp, "tcp", "velocity", 3) if tcp.get("velocity") is not None else []
    b = _read(tcp_file, [t_col["tcp"], *_columns(tcp, "tcp", "position", 3),
                         *_columns(tcp, "tcp", "orientation", CONVENTIONS[conv]), *vel_cols])
    t_tcp = b[:, 0] * _unit(tcp, "tcp", "time", TIME_UNITS)
    _increasing(t_tcp, tcp_file)
    k = 4 + CONVENTIONS[conv]
    s = Streams(t_imu, a[:, 1:4] * _unit(imu, "imu", "gyro", UNITS["gyro"]),
                a[:, 4:7] * _unit(imu, "imu", "accel", UNITS["accel"]), source=str(map_path))
    s.pose_t = t_tcp
    s.tcp_pos = b[:, 1:4] * _unit(tcp, "tcp", "position", UNITS["position"])
    s.tcp_quat = _orientation(b[:, 4:k], conv, tcp_file)
    if vel_cols:
        s.tcp_vel = b[:, k:k + 3] * _unit(tcp, "tcp", "velocity", UNITS["velocity"])
    return s


def _orientation(o: np.ndarray, conv: str, path: pathlib.Path) -> np.ndarray:
    if conv == "xyzw":
        q = o
    elif conv == "wxyz":
        q = o[:, [1, 2, 3, 0]]
    else:
        ang = o if conv == "rpy_rad" else np.radians(o)
        q = np.array([matrix_to_quat(rotvec_to_matrix(np.array([0.0, 0.0, z])) @ rotvec_to_matrix(np.array([0.0, y, 0.0]))
                                     @ rotvec_to_matrix(np.array([x, 0.0, 0.0]))) for x, y, z in ang])
    n = np.linalg.norm(q, axis=1)
    bad = np.abs(n - 1.0) > 1e-3
    if bad.any():
        i = int(np.argmax(bad))
        raise ImportFailure(f"{path}: row {i + 2}: the orientation is no unit quaternion (norm {n[i]:.4g})")
    return q
