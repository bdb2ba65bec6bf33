"""Logs that labs already have, as tecdar-recording/1 (issue 48 §6): `tecdard import`.

- A rosbag2 (a directory with metadata.yaml, sqlite3 or MCAP storage), a ROS 1 bag, or a bare MCAP
  file of ROS 2 messages: `sensor_msgs/msg/Imu`, and the TCP's pose from `sensor_msgs/msg/JointState`
  through the arm's model (forward kinematics) or from `/tf` (a chain of `tf2_msgs/msg/TFMessage`
  transforms from a base frame to the tool's). rosbags reads the bags; the `mcap` package reads a
  bare MCAP file and rosbags' type store decodes its CDR.
- CSV files, with a small YAML naming their columns and units (CSV_DOC).

The calibrated mount (imu.imu_in_tcp_quat) goes into the recording and the calibrated clock offset
(imu.time_offset_s) comes off the IMU's stamps, so `localize`, `plot` and `calibrate-eta` run on
the lab's data as on the daemon's. Bad input is refused with one line naming the topic, column or
row (ImportFailure).
"""
from __future__ import annotations

import math
import pathlib
import struct
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import matrix_to_quat, quat_to_matrix
from tecdard.recording.format import Recording

MAX_ROWS = 50_000_000          # samples per stream at most (a day at 500 Hz): beyond, a log is not one recording


class ImportFailure(ValueError):
    """What keeps a log from being imported, in one line naming the topic, column or row."""


@dataclass
class Streams:
    """What a log holds, as read: the IMU's samples, and the TCP's poses or the joints'."""
    imu_t: np.ndarray                      # (n,) s
    gyro: np.ndarray                       # (n, 3) rad/s, the IMU's frame
    accel: np.ndarray                      # (n, 3) m/s^2
    pose_t: np.ndarray | None = None       # (m,) s
    tcp_pos: np.ndarray | None = None      # (m, 3) m, world
    tcp_quat: np.ndarray | None = None     # (m, 4) (x, y, z, w), world <- TCP
    tcp_vel: np.ndarray | None = None      # (m, 3) m/s
    joint_t: np.ndarray | None = None      # (k,) s
    joint_names: list | None = None
    q: np.ndarray | None = None            # (k, nq) rad, in joint_names' order
    source: str = ""


def _ordered(t: np.ndarray, what: str, *arrays):
    """The samples sorted by time, exact repeats dropped (a bag's stamps need not come in order);
    ImportFailure when a stream is empty, too long, or not finite."""
    t = np.asarray(t, float)
    if len(t) == 0:
        raise ImportFailure(f"{what}: no samples")
    if len(t) > MAX_ROWS:
        raise ImportFailure(f"{what}: {len(t)} samples, at most {MAX_ROWS}")
    bad = ~np.isfinite(t)
    for a in arrays:
        bad |= ~np.all(np.isfinite(np.asarray(a, float).reshape(len(t), -1)), axis=1)
    if bad.any():
        raise ImportFailure(f"{what}: sample {int(np.argmax(bad))} is not finite")
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return (t[keep], *(np.asarray(a, float)[order][keep] for a in arrays))


def to_recording(s: Streams, mount_quat=(0.0, 0.0, 0.0, 1.0), time_offset_s: float = 0.0, model=None,
                 meta: dict | None = None) -> Recording:
    """The streams as a recording: the TCP from the poses, or from the joints through `model`
    (robots.model.ArmModel, its joints matched by name); the IMU's stamps less `time_offset_s`."""
    imu_t, gyro, accel = _ordered(s.imu_t, "the IMU", s.gyro, s.accel)
    if s.pose_t is not None:
        pose_t, pos, quat = _ordered(s.pose_t, "the TCP's poses", s.tcp_pos, s.tcp_quat)
        vel = None
    elif s.joint_t is not None:
        if model is None:
            raise ImportFailure("the log has joint states and no TCP poses: give the arm (--config, or --model "
                                "and the tool) to compute the TCP from them")
        pose_t, pos, quat = _forward(s, model)
        vel = None
    else:
        raise ImportFailure("no TCP poses or joint states in the log: name them (--joints-topic, --tf BASE:TOOL)")
    norms = np.linalg.norm(quat, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        i = int(np.argmax(np.abs(norms - 1.0) > 1e-3))
        raise ImportFailure(f"the TCP's orientation at sample {i} is no unit quaternion (norm {norms[i]:.4g})")
    quat = quat / norms[:, None]
    mount = np.asarray(mount_quat, float)
    if mount.shape != (4,) or not np.all(np.isfinite(mount)) or abs(float(np.linalg.norm(mount)) - 1.0) > 1e-3:
        raise ImportFailure(f"the mount: expected a unit quaternion (x, y, z, w), got {mount.tolist()}")
    overlap = min(imu_t[-1] - time_offset_s, pose_t[-1]) - max(imu_t[0] - time_offset_s, pose_t[0])
    if overlap <= 0:
        raise ImportFailure(f"the IMU ({imu_t[0]:.3f}..{imu_t[-1]:.3f} s) and the TCP ({pose_t[0]:.3f}.."
                            f"{pose_t[-1]:.3f} s) do not overlap in time: are both stamped on one clock?")
    return Recording(imu_t=imu_t - time_offset_s, gyro=gyro, accel=accel, tcp_t=pose_t, tcp_pos=pos, tcp_quat=quat,
                     imu_in_tcp_quat=mount / np.linalg.norm(mount), tcp_vel=vel,
                     meta={"imported_from": s.source, "imu_time_offset_s": time_offset_s, **(meta or {})})


def _forward(s: Streams, model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The TCP's poses from the joint states through the arm's model, the joints matched by name."""
    names = list(model.joint_names)
    index = {n: i for i, n in enumerate(s.joint_names or [])}
    missing = [n for n in names if n not in index]
    if missing:
        raise ImportFailure(f"the joint states name {', '.join(list(index)[:8]) or 'no joint'}; the model's joints "
                            f"are {', '.join(names)} (missing: {', '.join(missing)})")
    cols = [index[n] for n in names]
    t, q = _ordered(s.joint_t, "the joint states", s.q[:, cols])
    pos, quat = np.empty((len(t), 3)), np.empty((len(t), 4))
    for k in range(len(t)):
        oM = model.fk(q[k])
        pos[k], quat[k] = oM.translation, matrix_to_quat(oM.rotation)
    return t, pos, quat


# -- bags ------------------------------------------------------------------------------------------
def _stamp(msg, log_ns: int) -> float:
    """The message's header stamp, s; its log time where the header has none (zero)."""
    st = msg.header.stamp
    t = st.sec + st.nanosec * 1e-9
    return t if t > 0 else log_ns * 1e-9


def _messages(path: pathlib.Path):
    """(topic, type name, message, log time ns) of every message in a bag or a bare MCAP file."""
    if path.is_file() and path.suffix == ".mcap" and not (path.parent / "metadata.yaml").exists():
        yield from _mcap_messages(path)
        return
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
            for conn, log_ns, raw in reader.messages():
                yield conn.topic, conn.msgtype, reader.deserialize(raw, conn.msgtype), log_ns
    except AnyReaderError as exc:
        raise ImportFailure(f"{path}: not a readable bag ({str(exc).splitlines()[0][:160]})") from None


def _mcap_messages(path: pathlib.Path):
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        with open(path, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                name = schema.name if schema is not None else ""
                if channel.message_encoding != "cdr" or name not in store.types:
                    continue                          # not ROS 2 CDR, or a type this import does not read
                yield channel.topic, name, store.deserialize_cdr(message.data, name), message.log_time
    except (McapError, EOFError, ValueError, OSError, struct.error) as exc:
        raise ImportFailure(f"{path}: not a readable MCAP file ({str(exc).splitlines()[0][:160]})") from None


IMU_TYPE, JOINTS_TYPE, TF_TYPE = "sensor_msgs/msg/Imu", "sensor_msgs/msg/JointState", "tf2_msgs/msg/TFMessage"


def read_bag(path, imu_topic: str | None = None, joints_topic: str | None = None, tf: tuple | None = None) -> Streams:
    """The IMU's samples and the joints' (or, with tf = (base, tool), the TCP's poses from /tf and
    /tf_static) from a bag or a bare MCAP file. Each topic defaults to the only one of its type."""
    path = pathlib.Path(path)
    if not path.exists():
        raise ImportFailure(f"{path}: no such file or directory")
    imu: dict = {}
    joints: dict = {}
    edges: dict = {}
    types: dict = {}
    for topic, typ, msg, log_ns in _messages(path):
        types.setdefault(topic, typ)
        if typ == IMU_TYPE:
            t = _stamp(msg, log_ns)
            av, la = msg.angular_velocity, msg.linear_acceleration
            imu.setdefault(topic, []).append((t, av.x, av.y, av.z, la.x, la.y, la.z))
        elif typ == JOINTS_TYPE:
            joints.setdefault(topic, []).append((_stamp(msg, log_ns), list(msg.name), list(msg.position)))
        elif typ == TF_TYPE and tf is not None:
            for tr in msg.transforms:
                st = tr.header.stamp
                t = st.sec + st.nanosec * 1e-9 if (st.sec or st.nanosec) else log_ns * 1e-9
                p, r = tr.transform.translation, tr.transform.rotation
                edges.setdefault((tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")), []).append(
                    (t, p.x, p.y, p.z, r.x, r.y, r.z, r.w, topic == "/tf_static"))
    rows = np.array(imu[_pick(imu, imu_topic, IMU_TYPE, types)])
    s = Streams(rows[:, 0], rows[:, 1:4], rows[:, 4:7], source=str(path))
    if tf is not None:
        s.pose_t, s.tcp_pos, s.tcp_quat = _tf_chain(edges, *tf)
    else:
        samples = joints[_pick(joints, joints_topic, JOINTS_TYPE, types)]
        s.joint_names = samples[0][1]
        odd = next((k for k, (_, names, pos) in enumerate(samples)
                    if names != s.joint_names or len(pos) != len(names)), None)
        if odd is not None:
            raise ImportFailure(f"joint states message {odd}: its names or positions differ from the first's "
                                f"({len(samples[odd][1])} names, {len(samples[odd][2])} positions)")
        s.joint_t = np.array([x[0] for x in samples])
        s.q = np.array([x[2] for x in samples], float)
    return s


def _pick(found: dict, topic: str | None, typ: str, types: dict) -> str:
    if topic is not None:
        if topic not in found:
            what = f"is a {types[topic]}" if topic in types else "is not in the log"
            raise ImportFailure(f"{topic}: {what}, not a {typ} topic with messages")
        return topic
    if len(found) == 1:
        return next(iter(found))
    if not found:
        raise ImportFailure(f"no {typ} messages in the log (its topics: {', '.join(sorted(types)) or 'none'})")
    raise ImportFailure(f"several {typ} topics ({', '.join(sorted(found))}): name one")


def _tf_chain(edges: dict, base: str, tool: str):
    """The tool's pose in the base frame from the transforms' chain, at the stamps of its most
    frequent dynamic link (the others held, static ones as they are)."""
    parent = {child: par for (par, child) in edges}
    chain, frame = [], tool
    while frame != base:
        if frame not in parent:
            known = ", ".join(sorted({f for e in edges for f in e})) or "none"
            raise ImportFailure(f"/tf: no chain of transforms from {base} to {tool} (frames: {known})")
        chain.append((parent[frame], frame))
        frame = parent[frame]
        if len(chain) > 64:
            raise ImportFailure(f"/tf: the frames from {tool} loop")
    chain.reverse()
    series = {e: np.array(edges[e], float) for e in chain}
    dynamic = [e for e in chain if not series[e][:, 8].all()]
    clock = max(dynamic, key=lambda e: len(series[e])) if dynamic else chain[-1]
    t = np.unique(series[clock][:, 0])
    R = np.tile(np.eye(3), (len(t), 1, 1))
    p = np.zeros((len(t), 3))
    for e in chain:
        rows = series[e][np.argsort(series[e][:, 0], kind="stable")]
        j = np.clip(np.searchsorted(rows[:, 0], t, side="right") - 1, 0, len(rows) - 1)
        Re = quat_to_matrix(rows[j, 4:8] / np.linalg.norm(rows[j, 4:8], axis=1, keepdims=True))
        p = p + np.einsum("nij,nj->ni", R, rows[j, 1:4])
        R = R @ Re
    return t, p, np.array([matrix_to_quat(Rk) for Rk in R])


def angle_deg(a, b) -> float:
    """Degrees between two quaternions (x, y, z, w)."""
    return math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(a, b))))))
