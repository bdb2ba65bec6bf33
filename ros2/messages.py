"""The daemon's values as ROS 2 messages (rosbags message objects), and ROS 2 requests as command payloads.

Nothing here touches Zenoh; everything runs on the main thread's publish pass. Positions are in the
robot's base frame (`base_frame`), SI units, quaternions (x, y, z, w); stamps are the time a value
refers to, on the system clock.
"""
from __future__ import annotations

import json
import math

import numpy as np

from tecdard.control.geometry import matrix_to_quat

UNKNOWN_ORIENTATION_VAR = 1e9       # rad^2: the contact's orientation block says "unknown" (no estimate of it)
MARKER_NS = "tecdar_contact"
SPHERE_ID, ARROW_ID = 0, 1
ARROW_LENGTH_M = 0.1
MIN_SPHERE_M = 0.001                # a sphere is drawn at least this wide, however small its 3 sigma
MAX_SPHERE_M = 1.0
FLAG_DEFAULT, FLAG_TRUE, FLAG_FALSE = 0, 1, 2     # a tri-state flag of tecdar_msgs' requests

# Marker types and actions (visualization_msgs/msg/Marker)
ARROW, SPHERE = 0, 2
ADD, DELETE = 0, 2
# DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


def ros_time(ts, t_s: float):
    """builtin_interfaces/Time of seconds since the epoch."""
    t_ns = int(round(t_s * 1e9)) if math.isfinite(t_s) else 0
    t_ns = max(t_ns, 0)
    return ts.cls("builtin_interfaces/msg/Time")(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def header(ts, t_s: float, frame_id: str):
    return ts.cls("std_msgs/msg/Header")(stamp=ros_time(ts, t_s), frame_id=frame_id)


IDENTITY = (0.0, 0.0, 0.0, 1.0)


def axis_quat(axis) -> tuple:
    """A rotation whose x axis is `axis` (unit, base frame), as (x, y, z, w); identity for None. Plain
    floats: this runs for every estimate on the publish pass, where numpy's small-array calls cost more
    than the arithmetic."""
    if axis is None:
        return IDENTITY
    ax, ay, az = (float(v) for v in axis)
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if not math.isfinite(n) or n < 1e-9:
        return IDENTITY
    ax, ay, az = ax / n, ay / n, az / n
    hx, hy, hz = (0.0, 0.0, 1.0) if abs(az) < 0.9 else (0.0, 1.0, 0.0)
    yx, yy, yz = hy * az - hz * ay, hz * ax - hx * az, hx * ay - hy * ax       # y = helper x axis
    m = math.sqrt(yx * yx + yy * yy + yz * yz)
    yx, yy, yz = yx / m, yy / m, yz / m
    zx, zy, zz = ay * yz - az * yy, az * yx - ax * yz, ax * yy - ay * yx       # z = x x y
    return tuple(matrix_to_quat(np.array([[ax, yx, zx], [ay, yy, zy], [az, yz, zz]])).tolist())


def _pose(ts, p, q):
    P, Q, Pose = (ts.cls(t) for t in ("geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion",
                                      "geometry_msgs/msg/Pose"))
    return Pose(position=P(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def contact(ts, est, t_wall: float, frame: str, q=None):
    """geometry_msgs/PoseWithCovarianceStamped of a ContactEstimate: the estimate, its axis (x) where
    there is one (`q`: axis_quat of it, when the caller has it), its position covariance, and an
    orientation block of UNKNOWN_ORIENTATION_VAR."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.asarray(est.cov, float)
    cov[3:, 3:] = np.eye(3) * UNKNOWN_ORIENTATION_VAR
    PwC = ts.cls("geometry_msgs/msg/PoseWithCovariance")
    return ts.cls("geometry_msgs/msg/PoseWithCovarianceStamped")(
        header=header(ts, t_wall, frame),
        pose=PwC(pose=_pose(ts, est.p, axis_quat(est.axis) if q is None else q), covariance=cov.ravel()))


_STATIC: dict = {}


def _marker_statics(ts) -> dict:
    """A marker's parts that never change (no texture, no mesh, no lifetime), built once per typestore."""
    if id(ts) not in _STATIC:
        empty = np.zeros(0, np.uint8)
        _STATIC[id(ts)] = dict(
            lifetime=ts.cls("builtin_interfaces/msg/Duration")(sec=0, nanosec=0),
            texture=ts.cls("sensor_msgs/msg/CompressedImage")(header=header(ts, 0.0, ""), format="", data=empty),
            mesh_file=ts.cls("visualization_msgs/msg/MeshFile")(filename="", data=empty))
    return _STATIC[id(ts)]


def _marker(ts, hdr, ident: int, kind: int, action: int, p, q, scale, rgba):
    M = ts.cls("visualization_msgs/msg/Marker")
    V, C = ts.cls("geometry_msgs/msg/Vector3"), ts.cls("std_msgs/msg/ColorRGBA")
    return M(header=hdr, ns=MARKER_NS, id=ident, type=kind, action=action, pose=_pose(ts, p, q),
             scale=V(x=float(scale[0]), y=float(scale[1]), z=float(scale[2])),
             color=C(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]), frame_locked=False, points=[], colors=[],
             texture_resource="", uv_coordinates=[], text="", mesh_resource="", mesh_use_embedded_materials=False,
             **_marker_statics(ts))


def contact_markers(ts, est, t_wall: float, frame: str, q=None) -> list:
    """A sphere at the estimate as wide as its 3 sigma per axis, and for a line contact an arrow along
    its axis (deleted while there is none)."""
    hdr = header(ts, t_wall, frame)
    std = np.asarray(est.std, float)
    size = np.clip(np.where(np.isfinite(std), 6.0 * std, MAX_SPHERE_M), MIN_SPHERE_M, MAX_SPHERE_M)
    colour = (0.1, 0.8, 0.2, 0.6) if est.converged else (1.0, 0.6, 0.0, 0.6)
    out = [_marker(ts, hdr, SPHERE_ID, SPHERE, ADD, est.p, (0.0, 0.0, 0.0, 1.0), size, colour)]
    if est.axis is not None:
        out.append(_marker(ts, hdr, ARROW_ID, ARROW, ADD, est.p, axis_quat(est.axis) if q is None else q,
                           (ARROW_LENGTH_M, 0.004, 0.004), (0.2, 0.4, 1.0, 0.9)))
    else:
        out.append(_marker(ts, hdr, ARROW_ID, ARROW, DELETE, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                           (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0)))
    return out


def contact_tf(ts, est, t_wall: float, frame: str, child: str, q=None):
    """tf2_msgs/TFMessage: base_frame -> `<robot>/contact`."""
    V, Q = ts.cls("geometry_msgs/msg/Vector3"), ts.cls("geometry_msgs/msg/Quaternion")
    q = axis_quat(est.axis) if q is None else q
    tr = ts.cls("geometry_msgs/msg/Transform")(translation=V(x=float(est.p[0]), y=float(est.p[1]),
                                                               z=float(est.p[2])),
                                                 rotation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                            w=float(q[3])))
    stamped = ts.cls("geometry_msgs/msg/TransformStamped")(header=header(ts, t_wall, frame), child_frame_id=child,
                                                           transform=tr)
    return ts.cls("tf2_msgs/msg/TFMessage")(transforms=[stamped])


def tcp_pose(ts, p, q, t_wall: float, frame: str):
    return ts.cls("geometry_msgs/msg/PoseStamped")(header=header(ts, t_wall, frame), pose=_pose(ts, p, q))


def wrench(ts, force_n, torque_nm, t_wall: float, frame: str):
    """geometry_msgs/WrenchStamped of `state.wrench`: the arm's own estimate at the TCP in `frame` (the base), N and
    N m; a torque the arm does not give (the simulator's) is NaN, never a zero that reads as measured."""
    V = ts.cls("geometry_msgs/msg/Vector3")
    torque = [float("nan")] * 3 if torque_nm is None else torque_nm
    return ts.cls("geometry_msgs/msg/WrenchStamped")(
        header=header(ts, t_wall, frame), wrench=ts.cls("geometry_msgs/msg/Wrench")(
            force=V(x=float(force_n[0]), y=float(force_n[1]), z=float(force_n[2])),
            torque=V(x=float(torque[0]), y=float(torque[1]), z=float(torque[2]))))


def imu(ts, t_wall: float, gyro, accel, frame: str):
    """sensor_msgs/Imu of one averaged block: rad/s and m/s^2 in the IMU's frame; no orientation
    (orientation_covariance[0] = -1), covariances unknown (zeros)."""
    V, Q = ts.cls("geometry_msgs/msg/Vector3"), ts.cls("geometry_msgs/msg/Quaternion")
    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0
    return ts.cls("sensor_msgs/msg/Imu")(
        header=header(ts, t_wall, frame), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=no_orientation,
        angular_velocity=V(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=V(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
        linear_acceleration_covariance=np.zeros(9))


def event(ts, body: dict, t_wall: float, text: str):
    """tecdar_msgs/Event of an event of the Zenoh interface (`text`: its JSON)."""
    task = body.get("task")
    task = task if isinstance(task, str) else ""
    return ts.cls("tecdar_msgs/msg/Event")(stamp=ros_time(ts, t_wall), kind=str(body.get("kind", "")),
                                           task=task, detail_json=text)


def diagnostics(ts, t_wall: float, statuses: list):
    """diagnostic_msgs/DiagnosticArray of (name, level, message, {key: value}) tuples."""
    KV, DS = ts.cls("diagnostic_msgs/msg/KeyValue"), ts.cls("diagnostic_msgs/msg/DiagnosticStatus")
    return ts.cls("diagnostic_msgs/msg/DiagnosticArray")(
        header=header(ts, t_wall, ""),
        status=[DS(level=int(level), name=name, message=message, hardware_id="tecdard",
                   values=[KV(key=str(k), value=str(v)) for k, v in values.items()])
                for name, level, message, values in statuses])


# -- requests in ----------------------------------------------------------------------------------
ABSENT_KINDS = ("number", "direction", "numbers", "choice", "bool", "int_choice", "grid")


def request_payload(fields: tuple, req) -> dict:
    """A tecdar_msgs request as the Zenoh interface's command payload: a NaN number, an empty array or
    string and a FLAG_DEFAULT flag (0 for a choice of numbers) are left out, so that the same
    validation applies its default or says the field is required."""
    out = {}
    for f in fields:
        v = getattr(req, f.name)
        if f.kind == "number":
            v = float(v)
            if math.isnan(v):
                continue
            out[f.name] = v if math.isfinite(v) else str(v)       # +-inf: a clear bad_type, not a JSON error
        elif f.kind in ("direction", "numbers", "grid"):
            if len(v) == 0:
                continue
            values = [float(x) for x in v] if f.kind != "grid" else [int(x) for x in v]
            out[f.name] = [x if not isinstance(x, float) or math.isfinite(x) else str(x) for x in values]
        elif f.kind == "choice":
            if v != "":
                out[f.name] = str(v)
        elif f.kind == "bool":
            if int(v) != FLAG_DEFAULT:
                out[f.name] = {FLAG_TRUE: True, FLAG_FALSE: False}.get(int(v), int(v))
        elif f.kind == "int_choice":
            if int(v) != 0:
                out[f.name] = int(v)
        else:
            raise ValueError(f"{f.name}: no ROS 2 field kind for {f.kind!r}")
    return out


def task_response(ts, srv_type: str, reply: dict):
    """A tecdar_msgs task verb's (or Cancel's) response of the Zenoh interface's reply."""
    err = reply.get("error") or {}
    fields = dict(ok=bool(reply.get("ok")), error_code=str(err.get("code", "")),
                  error_message=str(err.get("message", "")))
    if not srv_type.endswith("/Cancel"):
        fields["task"] = str(reply.get("task", "") or "")
    return ts.cls(srv_type + "_Response")(**fields)


def trigger_response(ts, reply: dict):
    err = reply.get("error") or {}
    ok = bool(reply.get("ok"))
    message = "stopped: the arm is at rest" if ok else f"{err.get('code', '')}: {err.get('message', '')}"
    return ts.cls("std_srvs/srv/Trigger_Response")(success=ok, message=message)


def status_response(ts, srv_type: str, reply: dict):
    """tecdar_msgs/Status's response: the state's mode, task, faults and latest contact, and the whole
    state as JSON."""
    err = reply.get("error") or {}
    state = reply.get("state") or {}
    task = state.get("task") or {}
    faults = state.get("faults") or []
    c = state.get("contact") or None
    P = ts.cls("geometry_msgs/msg/Point")
    p = (c or {}).get("p") or [0.0, 0.0, 0.0]
    std = (c or {}).get("std") or [0.0, 0.0, 0.0]
    return ts.cls(srv_type + "_Response")(
        ok=bool(reply.get("ok")), mode=str(state.get("mode", "")), task_id=str(task.get("id", "") or ""),
        task_kind=str(task.get("kind", "") or ""), task_phase=str(task.get("phase", "") or ""),
        task_progress=float(task.get("progress", 0.0) or 0.0),
        fault_codes=[str(f.get("code", "")) for f in faults], fault_messages=[str(f.get("message", "")) for f in faults],
        has_contact=c is not None, contact_position=P(x=_num(p[0]), y=_num(p[1]), z=_num(p[2])),
        contact_std=np.array([_num(x) for x in std[:3]], dtype=np.float64),
        contact_converged=bool((c or {}).get("converged", False)),
        state_json=json.dumps(state, separators=(",", ":")) if state else "",
        error_code=str(err.get("code", "")), error_message=str(err.get("message", "")))


def _num(x) -> float:
    return float(x) if isinstance(x, (int, float)) else math.nan
