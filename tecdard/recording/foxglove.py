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
- `/events`: foxglove Log messages, the event as JSON text.
"""
from __future__ import annotations

import json

import foxglove
import numpy as np
from foxglove.channels import FrameTransformsChannel, LogChannel, SceneUpdateChannel
from foxglove.messages import (Color, FrameTransform, FrameTransforms, LinePrimitive, Log, LogLevel, Point3, Pose,
                               Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, Timestamp, Vector3)

from tecdard.control.geometry import matrix_to_quat
from tecdard.safejson import json_ready

ELLIPSOID_MAX_M = 0.2          # a one-sigma ellipsoid is drawn at most this big per axis (a line contact's
                               # along-edge sigma is half a metre)
AXIS_HALF_LENGTH_M = 0.08      # the axis line is drawn this far each side of the estimate
IMU_SCHEMA = {"type": "object", "properties": {
    "t": {"type": "array", "items": {"type": "number"}},
    "gyro": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
    "accel": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}}}
TOPICS = ("/imu", "/tf", "/contact", "/events")


def _stamp(ns: int):
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _quat(R: np.ndarray):
    x, y, z, w = matrix_to_quat(np.asarray(R, float))
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


class Channels:
    """The four channels in a foxglove Context (an MCAP file's own, or the server's). Times given
    in seconds on the daemon's clock become `t - origin_s + epoch_s` (MCAP and Foxglove want
    nanoseconds since the Unix epoch, never negative)."""

    def __init__(self, context=None, origin_s: float = 0.0, epoch_s: float = 0.0):
        self.origin_s, self.epoch_s = float(origin_s), float(epoch_s)
        self.imu = foxglove.Channel("/imu", message_encoding="json", context=context,
                                    schema=foxglove.Schema(name="tecdar.ImuBatch", encoding="jsonschema",
                                                           data=json.dumps(IMU_SCHEMA).encode()))
        self.tf = FrameTransformsChannel("/tf", context=context)
        self.contact_ch = SceneUpdateChannel("/contact", context=context)
        self.events = LogChannel("/events", context=context)

    def _ns(self, t: float) -> int:
        return max(0, int(round((float(t) - self.origin_s + self.epoch_s) * 1e9)))

    def close(self) -> None:
        for ch in (self.imu, self.tf, self.contact_ch, self.events):
            ch.close()

    def imu_batch(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        if len(t):
            self.imu.log({"t": t.tolist(), "gyro": gyro.tolist(), "accel": accel.tolist()}, log_time=self._ns(t[-1]))

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
