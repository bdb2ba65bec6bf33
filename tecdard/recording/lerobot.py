"""Daemon recordings as a LeRobot v3 dataset (`tecdard export --lerobot DIR`), written with pyarrow alone.

One recording is one episode; one frame per control tick (50 fps, the daemon's tick), on the ticks' own
schedule: frame k is at t0 + k / 50 s, and holds
- `action`: the joint rates the tick at that time commanded (`live_cmd`; the tick ran up to half a period
  late, or was skipped, and then the one before held), rad/s;
- `observation.state`: the newest measured state at or before it (what the controller knew): q (rad), dq
  (rad/s), the TCP position (m) and orientation (x, y, z, w), world;
- `observation.wrench`: the arm's own estimate at the TCP, force N then torque N m, world; NaN where the arm
  gives none (the simulator's torque);
- `observation.imu`: the IMU window ending at it, float32 [n, 6] (gyro rad/s, then accel m/s^2, sensor frame,
  raw), n = the board's rate / 50 (133 at 6667 Hz): the samples the tick's estimate had;
- `observation.contact`: the newest live estimate at or before it: point (m, world), axis (world unit), one
  sigma per axis (m), valid (1, or 0 with NaN before the first estimate and for an axis not yet excited);
- the task: the verb and its arguments, as the daemon's task_started event gave them.

The layout is LeRobot's v3.0 (lerobot 0.4's `LeRobotDataset`): data/chunk-000/file-000.parquet, meta/info.json,
meta/stats.json, meta/tasks.parquet, meta/episodes/chunk-000/file-000.parquet (with each episode's onsets and
result), and a dataset card. The recordings stay the master record (docs/recordings.md)."""
from __future__ import annotations

import json
import math
import pathlib
import warnings
from dataclasses import dataclass

import numpy as np

from tecdard.recording.format import RecordingError, load_recording
from tecdard.recording.live import load_live

FPS = 50
CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000
DATA_FILES_SIZE_MB = 100
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)          # lerobot's DEFAULT_QUANTILES: its stats' q01 ... q99
INDEX_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                  "task_index": "int64"}


class DatasetError(ValueError):
    """A recording that cannot be an episode, or a dataset that cannot be written; one line."""


@dataclass
class Episode:
    frames: dict                 # feature -> (F, ...) array
    task: str
    meta: dict                   # onsets and the result, for meta/episodes
    imu_n: int
    joints: int


def _task_text(events: list) -> tuple[str, dict]:
    """The verb and its arguments as a task string (`rotate angle_deg=30 ...`), and its task_started event."""
    started = next((e for e in events if e.get("kind") == "task_started"), None)
    if started is None:
        return "idle", {}
    params = started.get("params") or {}
    args = " ".join(f"{k}={json.dumps(v, separators=(',', ':'))}" for k, v in sorted(params.items()))
    return f"{started.get('verb')} {args}".strip(), started


def episode_of(path: str | pathlib.Path) -> Episode:
    """One daemon recording as an episode's frames; DatasetError naming the file when it cannot be one."""
    name = pathlib.Path(path).name
    try:
        rec = load_recording(path)
        live = load_live(path, rec)
    except RecordingError as exc:
        raise DatasetError(f"{name}: {exc}") from None
    missing = [k for k, v in (("live_cmd", None if live is None else live.cmd),
                              ("live_q", None if live is None else live.q),
                              ("live_qd", None if live is None else live.qd)) if v is None]
    if live is None or missing:
        raise DatasetError(f"{name}: no {', '.join(missing) or 'live_* members'}: not a daemon recording with its "
                           f"ticks' commands (recorded before they were kept?)")
    n = max(1, round(rec.imu_rate_hz / FPS))
    cmd_t = live.cmd[:, 0]
    t_first = max(cmd_t[0], rec.tcp_t[0], rec.imu_t[min(n, len(rec.imu_t)) - 1])
    t_last = min(cmd_t[-1], rec.tcp_t[-1], rec.imu_t[-1])
    count = int(math.floor((t_last - t_first) * FPS + 1e-9)) + 1 if t_last >= t_first else 0
    if count < 2:
        raise DatasetError(f"{name}: under two ticks with the IMU, the arm's states and a command all present")
    t = t_first + np.arange(count) / FPS
    k_cmd = np.searchsorted(cmd_t, t + 0.5 / FPS, side="right") - 1
    j = np.searchsorted(rec.tcp_t, t, side="right") - 1
    end = np.searchsorted(rec.imu_t, t, side="right")
    window = end[:, None] - n + np.arange(n)[None, :]
    imu = np.concatenate([rec.gyro, rec.accel], axis=1)[np.clip(window, 0, None)]
    wrench = np.full((count, 6), np.nan) if live.wrench is None else live.wrench[j]
    frames = {
        "action": live.cmd[k_cmd, 1:],
        "observation.state": np.concatenate([live.q[j], live.qd[j], rec.tcp_pos[j], rec.tcp_quat[j]], axis=1),
        "observation.wrench": wrench,
        "observation.imu": imu,
        "observation.contact": _contact(live, t),
        "timestamp": (t - t[0]).astype(np.float32),
    }
    task, started = _task_text(live.events)
    onsets = sorted({e["t"] - t[0] for e in live.events if e.get("kind") == "contact_onset"})   # the pipeline's and
    # the daemon's event of one onset carry the same time
    ended = next((e for e in live.events if e.get("kind") in ("task_done", "task_failed")), {})
    meta = {"recording": name, "task_id": started.get("task"), "verb": started.get("verb"),
            "onsets_s": onsets, "outcome": ended.get("kind"), "result": ended.get("result") or ended.get("error"),
            "robot": rec.meta.get("robot")}
    return Episode(frames, task, meta, n, live.q.shape[1])


def _contact(live, t: np.ndarray) -> np.ndarray:
    """(F, 10): point, axis, sigmas, valid of the newest estimate at or before each time."""
    out = np.full((len(t), 10), np.nan)
    out[:, 9] = 0.0
    if len(live.est):
        k = np.searchsorted(live.est[:, 0], t, side="right") - 1
        have = k >= 0
        est = live.est[k[have]]
        out[have, 0:3] = est[:, 1:4]
        if live.axis is not None:
            out[have, 3:6] = live.axis[k[have]]
        out[have, 6:9] = est[:, 4:7]
        out[have, 9] = 1.0
    return out


def features(ep: Episode) -> dict:
    """info.json's features for episodes like `ep`."""
    q = [f"q{i}" for i in range(ep.joints)]
    return {
        "action": {"dtype": "float32", "shape": [ep.joints], "names": [f"qd_cmd{i}" for i in range(ep.joints)]},
        "observation.state": {"dtype": "float32", "shape": [2 * ep.joints + 7],
                              "names": q + [f"dq{i}" for i in range(ep.joints)] + ["x", "y", "z", "qx", "qy", "qz",
                                                                                   "qw"]},
        "observation.wrench": {"dtype": "float32", "shape": [6], "names": ["fx", "fy", "fz", "tx", "ty", "tz"]},
        "observation.imu": {"dtype": "float32", "shape": [ep.imu_n, 6], "names": None},
        "observation.contact": {"dtype": "float32", "shape": [10],
                                "names": ["px", "py", "pz", "ax", "ay", "az", "sx", "sy", "sz", "valid"]},
        **{k: {"dtype": d, "shape": [1], "names": None} for k, d in INDEX_FEATURES.items()},
    }


def _stats(values: np.ndarray) -> dict:
    """lerobot's per-feature statistics over the frames (axis 0), NaN-aware (a wrench's missing torque)."""
    v = values.astype(np.float64).reshape(len(values), -1)
    shape = values.shape[1:] or (1,)
    with warnings.catch_warnings():                  # an all-NaN column (a torque never given) is NaN, said once here
        warnings.simplefilter("ignore", RuntimeWarning)
        out = {"min": np.nanmin(v, 0), "max": np.nanmax(v, 0), "mean": np.nanmean(v, 0), "std": np.nanstd(v, 0)}
        out |= {f"q{round(q * 100):02d}": np.nanquantile(v, q, axis=0) for q in QUANTILES}
    stats = {k: a.reshape(shape).tolist() for k, a in out.items()}
    stats["count"] = [len(values)]
    return stats


def _hf_feature(ft: dict) -> dict:
    """A feature as `datasets` describes it in a parquet file's schema metadata (the "huggingface" key)."""
    value = {"dtype": ft["dtype"], "_type": "Value"}
    if ft["shape"] == [1]:
        return value
    if len(ft["shape"]) == 1:
        return {"feature": value, "length": ft["shape"][0], "_type": "List"}
    return {"shape": ft["shape"], "dtype": ft["dtype"], "_type": f"Array{len(ft['shape'])}D"}


def _arrow_type(pa, ft: dict):
    """The arrow storage of a feature as `datasets` gives it: a fixed-size list for a vector, nested lists for
    an ArrayND (datasets' extension type stores them so)."""
    scalar = pa.float32() if ft["dtype"] == "float32" else pa.int64()
    if ft["shape"] == [1]:
        return scalar
    if len(ft["shape"]) == 1:
        return pa.list_(scalar, ft["shape"][0])
    out = scalar
    for _ in ft["shape"]:
        out = pa.list_(out)
    return out


def _arrow_array(pa, values: np.ndarray, typ):
    """`values` (F, ...) as an arrow column of `typ`, built from the flat buffer (not through Python lists)."""
    if values.ndim == 1:
        return pa.array(values, typ)
    flat = pa.array(values.ravel())
    if values.ndim == 2:
        return pa.FixedSizeListArray.from_arrays(flat, values.shape[1])
    rows, n, m = values.shape
    inner = pa.ListArray.from_arrays(pa.array(np.arange(rows * n + 1, dtype=np.int32) * m), flat)
    return pa.ListArray.from_arrays(pa.array(np.arange(rows + 1, dtype=np.int32) * n), inner)


def write_dataset(out: pathlib.Path, episodes: list[Episode], robot_type: str | None) -> dict:
    """The episodes as a LeRobot v3 dataset under `out` (made, and empty); its info.json's content."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    feats = features(episodes[0])
    for ep in episodes[1:]:
        if features(ep) != feats:
            raise DatasetError(f"{ep.meta['recording']}: {ep.joints} joints and an IMU window of {ep.imu_n} "
                               f"samples, where the first episode has {episodes[0].joints} and {episodes[0].imu_n}: "
                               "one dataset holds one arm and one board rate")
    tasks = sorted({ep.task for ep in episodes})
    columns: dict[str, list] = {k: [] for k in feats}
    ep_rows, index = [], 0
    for e, ep in enumerate(episodes):
        length = len(ep.frames["timestamp"])
        for key, values in ep.frames.items():
            columns[key].append(values)
        columns["frame_index"].append(np.arange(length))
        columns["episode_index"].append(np.full(length, e))
        columns["index"].append(np.arange(index, index + length))
        columns["task_index"].append(np.full(length, tasks.index(ep.task)))
        stats = {k: _stats(np.asarray(v)) for k, v in ep.frames.items()} | {
            k: _stats(columns[k][-1]) for k in ("frame_index", "episode_index", "index", "task_index")}
        ep_rows.append({"episode_index": e, "tasks": [ep.task], "length": length,
                        "data/chunk_index": 0, "data/file_index": 0,
                        "dataset_from_index": index, "dataset_to_index": index + length,
                        "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                        "tecdar": json.dumps(ep.meta, default=str),
                        **{f"stats/{k}/{s}": v for k, st in stats.items() for s, v in st.items()}})
        index += length
    arrays, fields = [], []
    for key, ft in feats.items():
        values = np.concatenate(columns[key])
        typ = _arrow_type(pa, ft)
        dtype = np.float32 if ft["dtype"] == "float32" else np.int64
        arrays.append(_arrow_array(pa, values.astype(dtype), typ))
        fields.append(pa.field(key, typ))
    schema = pa.schema(fields, metadata={"huggingface": json.dumps(
        {"info": {"features": {k: _hf_feature(ft) for k, ft in feats.items()}}})})
    data = out / "data" / "chunk-000"
    data.mkdir(parents=True)
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), data / "file-000.parquet")
    meta = out / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(ep_rows), meta / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": tasks}),
                   meta / "tasks.parquet")
    all_frames = {k: np.concatenate(columns[k]) for k in feats}
    (meta / "stats.json").write_text(json.dumps({k: _stats(v) for k, v in all_frames.items()}, indent=1))
    info = {"codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": len(episodes),
            "total_frames": index, "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILES_SIZE_MB, "video_files_size_in_mb": 200, "fps": FPS,
            "splits": {"train": f"0:{len(episodes)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet", "video_path": None,
            "features": feats}
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    (out / "README.md").write_text(_card(info, episodes))
    return info


def _card(info: dict, episodes: list[Episode]) -> str:
    """The dataset card: what each feature is, in the units and frames it is in."""
    verbs = sorted({str(ep.meta.get("verb")) for ep in episodes})
    return f"""---
tags: [LeRobot, tecdar, tactile, contact]
configs:
- config_name: default
  data_files: data/*/*.parquet
---
# A tecdar dataset

{info['total_episodes']} episodes ({', '.join(verbs)}), {info['total_frames']} frames at {FPS} fps (the daemon's
control tick), from tecdar's daemon recordings (`tecdard export --lerobot`). Each recording is one episode; the
recordings are the master record. The arm: {info['robot_type']}.

| feature | shape | what it is |
|---|---|---|
| `action` | {info['features']['action']['shape']} | the joint rates the tick commanded, rad/s (zeros where it held the arm) |
| `observation.state` | {info['features']['observation.state']['shape']} | the newest measured state at or before the frame: q (rad), dq (rad/s), the TCP position (m) and orientation (x, y, z, w), world |
| `observation.wrench` | [6] | the arm's own estimate at the TCP: force (N), torque (N m), world; NaN where the arm gives none |
| `observation.imu` | {info['features']['observation.imu']['shape']} | the fingertip IMU's samples ending at the frame: gyro (rad/s), accel (m/s^2, gravity included), sensor frame, raw |
| `observation.contact` | [10] | the newest live estimate of the contact point or hinge: point (m, world), axis (world unit), one sigma per axis (m), valid (1 or 0; NaN where not yet estimated) |

The task is the verb and its arguments. meta/episodes holds each episode's onsets (s from its first frame),
outcome and result under `tecdar`.
"""
