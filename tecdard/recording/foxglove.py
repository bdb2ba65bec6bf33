"""Foxglove channels for what tecdar sees: the IMU (batched), the TCP as frame transforms, the contact
estimate as a 3D scene (its one-sigma ellipsoid, the hinge axis or edge line), and the events.

One `Channels` set serves both `tecdard export --mcap` (a recording written to an MCAP file) and
the daemon's live Foxglove WebSocket server (tecdard/viz.py). Messages are foxglove-sdk's
(PyPI `foxglove-sdk`, the `viz` extra).

Topics and frames:
- `/imu`: JSON `{"t": [...], "gyro": [[x, y, z], ...], "accel": [...]}`, s, rad/s and m/s^2 in
  the IMU's frame, one message per batch (about 10 ms);
- `/tf`: `world` -> `tcp` at every proprioception sample, and `tcp` -> `imu` (the mount);
- `/contact`: a SceneUpdate in `world`: the estimate's one-sigma ellipsoid and, once the rotation
  axis is known, the axis through the estimate (the hinge, or the edge of a line contact);
- `/events`: foxglove Log messages, the event as JSON text;
- `/imu/mean`: JSON `{"gyro": {"x", "y", "z"}, "accel": {...}}`, each batch's mean (about 100 Hz),
  scalar fields a Plot panel draws (`/imu/mean.gyro.x`);
- `/joint_states`: foxglove JointStates at each proprioception sample that has the joints (a daemon
  recording's `live_q`), with the arm's joint names;
- `/robot_description`: the arm's URDF (JSON `{"data": urdf}`, as ROS's std_msgs/String), once, for
  the 3D panel's URDF layer driven by `/joint_states`; `/tf` then also places its root link in `world`.

Times are wall-clock time: a daemon recording carries the offset of the wall clock from the
monotonic clock it stamps with (`meta.clock`), so an MCAP lines up with the rest of a lab's data. The
offset is written in the file's metadata (`tecdar`). A recording without one (`sim-record`, an old
daemon's) starts at the Unix epoch, and the metadata says so.
"""
from __future__ import annotations

import json

import foxglove
import numpy as np
from foxglove.channels import FrameTransformsChannel, JointStatesChannel, LogChannel, SceneUpdateChannel
from foxglove.messages import (Color, FrameTransform, FrameTransforms, JointState, JointStates, LinePrimitive, Log,
                               LogLevel, Point3, Pose, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, Timestamp,
                               Vector3)

from tecdard.control.geometry import matrix_to_quat
from tecdard.safejson import json_ready

ELLIPSOID_MAX_M = 0.2          # a one-sigma ellipsoid is drawn at most this big per axis (a line contact's
                               # along-edge sigma is half a metre)
AXIS_HALF_LENGTH_M = 0.08      # the axis line is drawn this far each side of the estimate
IMU_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "array", "items": {"type": "number"}},
    "gyro": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
    "accel": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}}}
TOPICS = ("/imu", "/tf", "/contact", "/events", "/imu/mean", "/joint_states", "/robot_description")
AXIS_FIELDS = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
IMU_MEAN_SCHEMA = {"type": "object", "properties": {"gyro": AXIS_FIELDS, "accel": AXIS_FIELDS,
                                                    "samples": {"type": "integer"}}}
STRING_SCHEMA = {"type": "object", "properties": {"data": {"type": "string"}}}
GRIPPER_SCHEMA = {"type": "object", "properties": {"width_m": {"type": ["number", "null"]},
                                                   "force_n": {"type": ["number", "null"]},
                                                   "grasped": {"type": ["boolean", "null"]}}}
_XYZ = {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}}
WRENCH_SCHEMA = {"type": "object", "properties": {"force_n": _XYZ, "torque_nm": {"oneOf": [_XYZ, {"type": "null"}]},
                                                  "frame_id": {"type": "string"}, "source": {"type": "string"}}}


def _stamp(ns: int):
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _quat(R: np.ndarray):
    x, y, z, w = matrix_to_quat(np.asarray(R, float))
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


class Channels:
    """The four channels in a foxglove Context (an MCAP file's own, or the server's). Times given
    in seconds on the daemon's clock become `t - origin_s + epoch_s` (MCAP and Foxglove want
    nanoseconds since the Unix epoch, never negative)."""

    def __init__(self, context=None, origin_s: float = 0.0, epoch_s: float = 0.0, arm: bool = True):
        """`arm`: the /joint_states, /robot_description and /gripper channels too (the export's; the live view
        has no joints or gripper states to send)."""
        self.origin_s, self.epoch_s = float(origin_s), float(epoch_s)
        self.imu = foxglove.Channel("/imu", message_encoding="json", context=context,
                                    schema=foxglove.Schema(name="tecdar.ImuBatch", encoding="jsonschema",
                                                           data=json.dumps(IMU_SCHEMA).encode()))
        self.tf = FrameTransformsChannel("/tf", context=context)
        self.contact_ch = SceneUpdateChannel("/contact", context=context)
        self.events = LogChannel("/events", context=context)
        self.imu_mean = foxglove.Channel("/imu/mean", message_encoding="json", context=context,
                                         schema=foxglove.Schema(name="tecdar.ImuMean", encoding="jsonschema",
                                                                data=json.dumps(IMU_MEAN_SCHEMA).encode()))
        self.joints = self.description = self.gripper_ch = self.wrench_ch = None
        if arm:
            self.gripper_ch = foxglove.Channel("/gripper", message_encoding="json", context=context,
                                               schema=foxglove.Schema(name="tecdar.Gripper", encoding="jsonschema",
                                                                      data=json.dumps(GRIPPER_SCHEMA).encode()))
            self.wrench_ch = foxglove.Channel("/wrench", message_encoding="json", context=context,
                                              schema=foxglove.Schema(name="tecdar.Wrench", encoding="jsonschema",
                                                                     data=json.dumps(WRENCH_SCHEMA).encode()))
            self.joints = JointStatesChannel("/joint_states", context=context)
            self.description = foxglove.Channel("/robot_description", message_encoding="json", context=context,
                                                schema=foxglove.Schema(name="std_msgs/msg/String",
                                                                       encoding="jsonschema",
                                                                       data=json.dumps(STRING_SCHEMA).encode()))

    def _ns(self, t: float) -> int:
        return max(0, int(round((float(t) - self.origin_s + self.epoch_s) * 1e9)))

    def close(self) -> None:
        for ch in (self.imu, self.tf, self.contact_ch, self.events, self.imu_mean, self.gripper_ch, self.wrench_ch,
                   self.joints, self.description):
            if ch is not None:
                ch.close()

    def imu_batch(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        if len(t):
            self.imu.log({"t": t.tolist(), "gyro": gyro.tolist(), "accel": accel.tolist()}, log_time=self._ns(t[-1]))
            g, a = np.mean(gyro, axis=0), np.mean(accel, axis=0)
            self.imu_mean.log({"gyro": dict(zip("xyz", map(float, g))), "accel": dict(zip("xyz", map(float, a))),
                               "samples": int(len(t))}, log_time=self._ns(t[-1]))

    def gripper(self, t: float, width_m: float | None, force_n: float | None, grasped: bool | None) -> None:
        """The gripper: its opening (m), its grip force (N) and whether it holds; null where it cannot say."""
        self.gripper_ch.log({"width_m": width_m, "force_n": force_n, "grasped": grasped}, log_time=self._ns(t))

    def wrench(self, t: float, wrench: np.ndarray, source: str) -> None:
        """The arm's own estimate of the external wrench at the TCP, world frame: force N, torque N m (null: none)."""
        torque = None if not np.all(np.isfinite(wrench[3:])) else dict(zip("xyz", map(float, wrench[3:])))
        self.wrench_ch.log({"force_n": dict(zip("xyz", map(float, wrench[:3]))), "torque_nm": torque,
                            "frame_id": "world", "source": source}, log_time=self._ns(t))

    def joint_states(self, t: float, names: list[str], q: np.ndarray) -> None:
        self.joints.log(JointStates(timestamp=_stamp(self._ns(t)),
                                    joints=[JointState(name=n, position=float(x)) for n, x in zip(names, q)]),
                        log_time=self._ns(t))

    def robot(self, t: float, desc: "RobotDescription") -> None:
        """The arm's URDF on /robot_description and its root link placed in `world` on /tf."""
        self.description.log({"data": desc.urdf}, log_time=self._ns(t))
        T = desc.world_root
        self.tf.log(FrameTransforms(transforms=[FrameTransform(
            timestamp=_stamp(self._ns(t)), parent_frame_id="world", child_frame_id=desc.root_link,
            translation=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])), rotation=_quat(T[:3, :3]))]),
            log_time=self._ns(t))

    def tcp(self, t: float, p: np.ndarray, R: np.ndarray, R_tcp_imu: np.ndarray | None = None) -> None:
        transforms = [FrameTransform(timestamp=_stamp(self._ns(t)), parent_frame_id="world", child_frame_id="tcp",
                                     translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                     rotation=_quat(R))]
        if R_tcp_imu is not None:
            transforms.append(FrameTransform(timestamp=_stamp(self._ns(t)), parent_frame_id="tcp", child_frame_id="imu",
                                             translation=Vector3(), rotation=_quat(R_tcp_imu)))
        self.tf.log(FrameTransforms(transforms=transforms), log_time=self._ns(t))

    def contact(self, t: float, p: np.ndarray, cov: np.ndarray, axis: np.ndarray | None, entity: str = "contact",
                rgba=(0.9, 0.3, 0.1, 0.5)) -> None:
        """The estimate at `p` (world, m) with covariance `cov` (3 x 3, m^2) and its axis (or None)."""
        vals, vecs = np.linalg.eigh(0.5 * (np.asarray(cov, float) + np.asarray(cov, float).T))
        if np.linalg.det(vecs) < 0:
            vecs[:, 0] = -vecs[:, 0]
        size = np.minimum(2.0 * np.sqrt(np.maximum(vals, 0.0)), ELLIPSOID_MAX_M)
        color = Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
        pos = Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
        spheres = [SpherePrimitive(pose=Pose(position=pos, orientation=_quat(vecs)),
                                   size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])), color=color)]
        lines = []
        if axis is not None and np.all(np.isfinite(axis)):
            a = np.asarray(axis, float) / max(float(np.linalg.norm(axis)), 1e-12)
            ends = [np.asarray(p, float) - AXIS_HALF_LENGTH_M * a, np.asarray(p, float) + AXIS_HALF_LENGTH_M * a]
            lines.append(LinePrimitive(points=[Point3(x=float(e[0]), y=float(e[1]), z=float(e[2])) for e in ends],
                                       thickness=0.002, color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=1.0)))
        self.contact_ch.log(SceneUpdate(entities=[SceneEntity(timestamp=_stamp(self._ns(t)), frame_id="world", id=entity,
                                                              spheres=spheres, lines=lines)]), log_time=self._ns(t))

    def event(self, t: float, event: dict) -> None:
        kind = str(event.get("kind", ""))
        level = LogLevel.Warning if kind in ("protective_stop", "fault", "task_failed", "warning") else LogLevel.Info
        text = json.dumps(json_ready(event), allow_nan=False)
        self.events.log(Log(timestamp=_stamp(self._ns(t)), level=level, message=text, name=kind),
                        log_time=self._ns(t))


# -- the arm, for the 3D panel ---------------------------------------------------------------------

# the URDF drawn for an arm whose model has none (the e-Series are built from UR's DH parameters):
# the CB3 arm of its size, whose joints have the same names
DRAWN_AS = {"ur3e": "ur3", "ur5e": "ur5", "ur10e": "ur10", "ur16e": "ur10"}


class RobotDescription:
    """An arm's URDF with its meshes as file:// paths on this host, its root link, the pose of that
    root in the daemon's world (4 x 4), and its joint names in the model's order."""

    def __init__(self, urdf: str, root_link: str, world_root: np.ndarray, joint_names: list[str], drawn_as: str):
        self.urdf, self.root_link, self.world_root = urdf, root_link, world_root
        self.joint_names, self.drawn_as = joint_names, drawn_as


def robot_description(model_name: str) -> RobotDescription | None:
    """The description of `model_name` (robot.model), or None for an arm without a URDF."""
    import re

    import pinocchio as pin

    from tecdard.robots import model as arm_models
    drawn = DRAWN_AS.get(model_name, model_name)
    rel = arm_models.ARMS.get(drawn, (None, None))[0]
    if rel is None:
        return None
    path = arm_models.robots_dir() / rel
    text = path.read_text()
    share = arm_models.robots_dir().parent          # .../share/example-robot-data
    text = re.sub(r"package://example-robot-data/", f"file://{share}/", text)
    full = pin.buildModelFromUrdf(str(path))
    data = full.createData()
    pin.framesForwardKinematics(full, data, pin.neutral(full))
    root = next(f.name for f in full.frames if f.type == pin.FrameType.BODY)
    if root == "world":             # UR's URDFs have a link of that name: ours is the daemon's frame
        root = "urdf_world"
        text = re.sub(r'(<(?:link|parent|child) (?:name|link)=")world(")', r"\1urdf_world\2", text)
    world_root = np.eye(4)
    if model_name in arm_models.UR_ARMS and full.existFrame(arm_models.ur_dh.CONTROLLER_BASE):
        # the daemon's world is the controller's base frame: the URDF's root sits at its inverse
        world_root = data.oMf[full.getFrameId(arm_models.ur_dh.CONTROLLER_BASE)].inverse().homogeneous
    ours = arm_models.ArmModel(model_name)
    names = [ours.model.names[j] for j in range(1, ours.model.njoints)]
    return RobotDescription(text, root, world_root, names, drawn)
