"""Recordings `tecdar-recording/1` (.npz): strict reading with one-line errors naming the key, and writing.

A recording is untrusted input. The reader never calls np.load on it: it opens the archive
itself, reads each member's .npy header, and checks the declared dtype, shape and size against
the zip directory and against limits (MAX_*), all before it allocates or decompresses anything.
A zip bomb, a header declaring terabytes, a bad CRC, broken deflate, a pickle or a truncated
member is then one RecordingError naming the key, in bounded time and memory.

Which members there are, their shapes and whether they are required is recording/members.py's table;
this module reads, checks and writes what it declares.
"""
from __future__ import annotations

import io
import json
import math
import pathlib
import zipfile
import zlib
from dataclasses import dataclass, field

import numpy as np

from tecdard.recording.members import CORE, MAX_IMU_SAMPLES, MEMBERS, TRUTH_PREFIX, Member
from tecdard.safejson import JsonLimitError, loads, show

FORMAT = "tecdar-recording/1"
QUAT_NORM_TOL = 1e-3
UNIT_TOL = 1e-3
MAX_DURATION_S = 3600.0          # from the first to the last sample of either stream
MAX_ABS_TIME_S = 1e10            # timestamps beyond this are no clock a rig keeps (300 years)
MAX_STRING_BYTES = 1 << 20       # `format` and `meta`
MAX_META_DEPTH = 32
MAX_HEADER_BYTES = 10_000        # numpy's own bound for a .npy header
MAX_TRUTH_BYTES = 8 * MAX_IMU_SAMPLES   # a truth_* member: at most a series as long as the IMU's may be
MAX_TRUTH_TOTAL_BYTES = 2 * MAX_TRUTH_BYTES
MAX_TRUTH_KEYS = 64
# The IMU's median sample rate: the onset detector's band (40-200 Hz by default) needs the rate above
# twice its top, and a fingertip IMU at under 100 Hz is no contact sensor (sim.imu.odr_hz's range).
IMU_RATE_RANGE_HZ = (100.0, 20_000.0)
# Magnitudes no rig records: ten times the LSM6DSR's widest full scales (4000 dps = 70 rad/s, 16 g),
# a TCP within 100 m of the base at under 100 m/s, a grip under 100 kN. Beyond them a value is a
# corrupt file, and its sums overflow inside the estimator.
ABS_MAX = {"gyro": 700.0, "accel": 1570.0, "tcp_pos": 100.0, "tcp_vel": 100.0, "grip_force": 1e5,
           "tcp_wrench": 1e5}      # N and N m: no arm estimates more


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
        """From a dict of the format's keys (e.g. sim.scenarios.generate); absent optionals are None."""
        return cls(**{m.attr: fields[m.key] if m.required else fields.get(m.key) for m in CORE if m.key != "format"}
                   | {"meta": fields.get("meta") or {}})

    @property
    def imu_rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.imu_t)))

    @property
    def tcp_rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.tcp_t)))

    @property
    def duration_s(self) -> float:
        return float(self.imu_t[-1] - self.imu_t[0])


class _Npz:
    """The members of an .npz archive, read one at a time after their declared size, dtype and
    shape have been checked (no np.load: nothing is allocated before the checks)."""

    def __init__(self, path: pathlib.Path):
        try:
            self.zf = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError) as exc:
            raise RecordingError(f"{path}: not a NumPy .npz file ({type(exc).__name__})") from None
        self.infos = {}
        for info in self.zf.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            self.infos.setdefault(name, info)

    def close(self) -> None:
        self.zf.close()

    def __contains__(self, key: str) -> bool:
        return key in self.infos

    def header(self, key: str):
        """(dtype, shape, fortran_order, data bytes, data offset) as the member declares them."""
        info = self.infos[key]
        try:
            with self.zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=MAX_HEADER_BYTES)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=MAX_HEADER_BYTES)
                else:
                    raise RecordingError(f"{key}: .npy format version {version} is not supported (1.0 or 2.0)")
                offset = f.tell()
        except RecordingError:
            raise
        except (ValueError, SyntaxError, TypeError, OSError, EOFError, zipfile.BadZipFile, zlib.error,
                NotImplementedError, RuntimeError) as exc:
            raise RecordingError(f"{key}: not a valid .npy member ({_why(exc)})") from None
        if dtype.hasobject:
            raise RecordingError(f"{key}: holds Python objects (pickled); refused")
        if dtype.fields is not None or dtype.subdtype is not None:
            raise RecordingError(f"{key}: a structured dtype {show(str(dtype))}; expected a plain array")
        if any(not isinstance(n, int) or n < 0 for n in shape) or len(shape) > 4:
            raise RecordingError(f"{key}: a header declaring shape {show(list(shape))}")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes != info.file_size - offset:
            raise RecordingError(f"{key}: the header declares shape {tuple(shape)} of {dtype} ({nbytes} bytes) but "
                                 f"the member holds {max(info.file_size - offset, 0)} bytes")
        return dtype, tuple(shape), fortran, nbytes, offset

    def read(self, key: str):
        """The member's array, once its header has passed the checks."""
        dtype, shape, fortran, nbytes, offset = self.header(key)
        try:
            buf = bytearray(nbytes)        # writable, and allocated only after the checks
            with self.zf.open(self.infos[key]) as f:
                f.read(offset)
                got = f.readinto(buf)
                f.read(1)                  # reaching the member's end checks its CRC
        except (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, RuntimeError) as exc:
            raise RecordingError(f"{key}: corrupt data in the archive ({_why(exc)})") from None
        if got != nbytes:
            raise RecordingError(f"{key}: truncated ({got} of {nbytes} bytes)")
        arr = np.frombuffer(buf, dtype=dtype)
        return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def _why(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text[:120]}" if text else type(exc).__name__


def _array(data: _Npz, key: str, shape: tuple, required: bool = True, rows_max: int | None = None,
           nan_ok: bool = False):
    """The key as float64 of `shape` (None entries: any length, at most rows_max; NaN only where `nan_ok`: a value
    the source did not give); RecordingError otherwise."""
    if key not in data:
        if required:
            raise RecordingError(f"{key}: missing required key")
        return None
    dtype, declared, *_ = data.header(key)
    if dtype.kind not in "fiu":
        raise RecordingError(f"{key}: expected a numeric array, got dtype {dtype}")
    if len(declared) != len(shape) or any(s is not None and s != a for s, a in zip(shape, declared)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise RecordingError(f"{key}: expected shape {want}, got {declared}")
    if rows_max is not None and declared and declared[0] > rows_max:
        raise RecordingError(f"{key}: {declared[0]} rows, at most {rows_max}")
    arr = np.asarray(data.read(key), dtype=np.float64)
    bad = np.isinf(arr) if nan_ok else ~np.isfinite(arr)
    if bad.any():
        row = int(np.argwhere(bad)[0][0]) if arr.ndim else 0
        raise RecordingError(f"{key}: contains {'inf' if nan_ok else 'NaN or inf'} (first at row {row})")
    limit = ABS_MAX.get(key)
    if limit is not None and arr.size:
        big = np.abs(arr) > limit
        if big.any():
            at = tuple(int(i) for i in np.argwhere(big)[0])
            raise RecordingError(f"{key}: {arr[at]:.6g} at row {at[0] if arr.ndim else 0} is beyond {limit:g}, "
                                 f"no rig's reading (a corrupt file?)")
    return arr


def _string(data: _Npz, key: str, required: bool) -> str | None:
    if key not in data:
        if required:
            raise RecordingError(f"{key}: missing required key")
        return None
    dtype, shape, _, nbytes, _ = data.header(key)
    if shape != () or dtype.kind not in "US":
        raise RecordingError(f"{key}: expected a string scalar, got dtype {dtype} shape {shape}")
    if nbytes > MAX_STRING_BYTES:
        raise RecordingError(f"{key}: a string of {nbytes} bytes, at most {MAX_STRING_BYTES}")
    value = data.read(key).item()
    if isinstance(value, bytes):
        try:
            return value.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise RecordingError(f"{key}: not UTF-8 (byte {exc.start})") from None
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise RecordingError(f"{key}: holds characters that are not Unicode text (lone surrogates)") from None
    return value


def _increasing(t: np.ndarray, key: str) -> None:
    if len(t) < 2:
        raise RecordingError(f"{key}: needs at least 2 samples, got {len(t)}")
    if np.abs(t).max() > MAX_ABS_TIME_S:
        raise RecordingError(f"{key}: timestamps beyond {MAX_ABS_TIME_S:g} s (got {show(float(np.abs(t).max()))})")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0)) + 1
        raise RecordingError(f"{key}: timestamps must be strictly increasing (row {i}: {float(t[i]):.9g} s after {float(t[i - 1]):.9g} s)")
    if t[-1] - t[0] > MAX_DURATION_S:
        raise RecordingError(f"{key}: spans {t[-1] - t[0]:.6g} s, at most {MAX_DURATION_S:g} s")


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
        raise RecordingError(f"{show(str(path), 200)}: no such file")
    data = _Npz(path)
    try:
        return _read(data)
    finally:
        data.close()


def _read(get: _Npz) -> Recording:
    values: dict = {}
    for m in CORE:
        value = _member(get, m, values)
        check = CHECKS.get(m.key)
        values[m.attr] = check(value) if check is not None and value is not None else value
    del values["format"]
    values["meta"] = values["meta"] or {}
    return Recording(**values)


def _member(get: _Npz, m: Member, values: dict):
    """One declared member as read, or None where an optional one is absent; the rows of a series are
    checked against its clock's (from the header, before the data are read)."""
    if m.kind != "array":
        return _string(get, m.key, m.required)
    rows_of = m.rows_of
    if rows_of is not None and not _rows(get, m.key, len(values[rows_of]), rows_of, m.required):
        return None
    shape = tuple(s if isinstance(s, int) else None for s in m.shape)
    return _array(get, m.key, shape, required=m.required, rows_max=m.rows_max)


def _format(fmt: str) -> str:
    if fmt != FORMAT:
        raise RecordingError(f"format: expected {FORMAT!r}, got {show(fmt)}")
    return fmt


def _imu_t(imu_t: np.ndarray) -> np.ndarray:
    _increasing(imu_t, "imu_t")
    rate = float(1.0 / np.median(np.diff(imu_t)))
    if not IMU_RATE_RANGE_HZ[0] <= rate <= IMU_RATE_RANGE_HZ[1]:
        raise RecordingError(f"imu_t: a median sample rate of {rate:.6g} Hz, expected "
                             f"{IMU_RATE_RANGE_HZ[0]:g}-{IMU_RATE_RANGE_HZ[1]:g} Hz")
    return imu_t


def _tcp_t(tcp_t: np.ndarray) -> np.ndarray:
    _increasing(tcp_t, "tcp_t")
    return tcp_t


def _plane_normal(normal: np.ndarray) -> np.ndarray:
    if abs(np.linalg.norm(normal) - 1.0) > UNIT_TOL:
        raise RecordingError(f"plane_normal: expected a unit vector, |n| = {np.linalg.norm(normal):.6f}")
    return normal / np.linalg.norm(normal)


def _meta(text: str) -> dict:
    try:
        meta = loads(text, max_depth=MAX_META_DEPTH)
    except JsonLimitError as exc:
        raise RecordingError(f"meta: not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise RecordingError(f"meta: expected a JSON object, got {type(meta).__name__}")
    return meta


# each declared member's own checks beyond its shape, rows and finite values (tests hold the keys to
# the table's)
CHECKS = {
    "format": _format, "imu_t": _imu_t, "tcp_t": _tcp_t,
    "tcp_quat": lambda q: _unit_quats(q, "tcp_quat"), "imu_in_tcp_quat": lambda q: _unit_quats(q, "imu_in_tcp_quat"),
    "plane_normal": _plane_normal, "meta": _meta,
}


def _rows(data: _Npz, key: str, n: int, of: str, required: bool = True) -> bool:
    """Whether `key` is there (RecordingError if required and not); its declared rows must be n
    (checked from the header, before its data are read)."""
    if key not in data:
        if required:
            raise RecordingError(f"{key}: missing required key")
        return False
    _, shape, *_ = data.header(key)
    if len(shape) >= 1 and shape[0] != n:
        raise RecordingError(f"{key}: has {shape[0]} rows but {of} has {n}")
    return True


def load_truth(path: str | pathlib.Path) -> dict:
    """The `truth_*` keys of a simulated recording (benchmarks and tests only; estimators never see
    them), each through the bounded reader: a member whose header declares more than
    MAX_TRUTH_BYTES, or that is not a plain array, is RecordingError naming it, before a byte of it
    is decompressed (a 1.6 MB file once took 1.2 GB and 21 s through np.load)."""
    data = _Npz(pathlib.Path(path))
    try:
        out, total = {}, 0
        for key in [k for k in data.infos if k.startswith(TRUTH_PREFIX)][:MAX_TRUTH_KEYS]:
            dtype, shape, _, nbytes, _ = data.header(key)
            total += nbytes
            if nbytes > MAX_TRUTH_BYTES or total > MAX_TRUTH_TOTAL_BYTES:
                raise RecordingError(f"{key}: {nbytes} bytes declared, at most {MAX_TRUTH_BYTES} for a truth "
                                     f"(and {MAX_TRUTH_TOTAL_BYTES} for them all)")
            if dtype.kind not in "fiuUb":
                raise RecordingError(f"{key}: dtype {show(str(dtype))}; expected numbers or a string")
            out[key[len(TRUTH_PREFIX):]] = data.read(key)
        return out
    finally:
        data.close()


def save_recording(path, rec: Recording, truth: dict | None = None, extra: dict | None = None,
                   compress: bool = True) -> None:
    """Write `rec` to a path or an open binary file; `truth` as truth_* keys, `extra` as they are (a
    daemon recording's live_* keys: each a member of recording/members.py's table, ValueError otherwise).
    `compress` False: a plain zip, written at disk speed."""
    arrays = {}
    for m in CORE:
        if m.key == "format":
            arrays["format"] = np.array(FORMAT)
        elif m.key == "meta":
            if rec.meta:
                arrays["meta"] = np.array(json.dumps(rec.meta))
        elif getattr(rec, m.attr) is not None:
            arrays[m.key] = getattr(rec, m.attr)
    for k, v in (truth or {}).items():
        arrays[f"{TRUTH_PREFIX}{k}"] = np.asarray(v)
    undeclared = [k for k in (extra or {}) if k not in MEMBERS or MEMBERS[k] in CORE]
    if undeclared:
        raise ValueError(f"{undeclared[0]}: no live member of tecdar-recording/1 (recording/members.py)")
    arrays.update(extra or {})
    write_npz(path, arrays, compress)


STORE_RATIO = 0.9            # a member whose sample deflates to more than this of its size is stored
RATIO_SAMPLE_BYTES = 1 << 16  # how much of a member that sample is


def write_npz(path, arrays: dict, compress: bool = True) -> None:
    """An .npz as np.savez_compressed writes it (np.save's .npy members in a zip, '.npz' added to a
    path without it), except that with `compress` a member is deflated only where that pays: the
    IMU's samples (float noise) deflate to about 95 % of their size, and inflating them was a tenth
    of `tecdard localize`'s time. Whether a member pays is judged on its first RATIO_SAMPLE_BYTES.
    np.load and every zip reader read both kinds of member."""
    if isinstance(path, (str, pathlib.PurePath)) and not str(path).endswith(".npz"):
        path = f"{path}.npz"
    with zipfile.ZipFile(path, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for key, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            data = buf.getbuffer()
            how = zipfile.ZIP_STORED
            if compress:
                sample = bytes(data[:RATIO_SAMPLE_BYTES])
                if len(zlib.compress(sample)) <= STORE_RATIO * len(sample):
                    how = zipfile.ZIP_DEFLATED
            zf.writestr(zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0)), data, compress_type=how)
