"""Rotation helpers in numpy: quaternions are (x, y, z, w), matrices map child -> parent."""
from __future__ import annotations

import math

import numpy as np


def cross3(a, b) -> np.ndarray:
    """a x b for two 3-vectors. np.cross costs ~0.2 ms a call in its axis handling, which made
    it the simulated arm's largest cost at 1 kHz; this is the same product in ~2 us."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs ~10x more on small arrays)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def skew(w: np.ndarray) -> np.ndarray:
    """[w]x, so that skew(w) @ r == cross(w, r)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) as (x, y, z, w) to rotation matrix(ces) (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) to unit quaternion (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def rotvec_to_matrix(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (axis * angle, rad) to rotation matrix."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    K = skew(phi)
    if angle < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + (np.sin(angle) / angle) * K + ((1 - np.cos(angle)) / angle**2) * K @ K


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Inverse of rotvec_to_matrix for angles in [0, pi)."""
    cos_a = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_a)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-8:
        return 0.5 * v
    return v * (angle / (2.0 * np.sin(angle)))


def relative_rotvec(R, R_ref) -> tuple[float, float, float]:
    """matrix_to_rotvec(R @ R_ref.T) in plain floats, for 3 x 3 nested lists (e.g. `R.tolist()`):
    a 1 kHz loop on 3-vectors pays more for numpy's per-call overhead than for the arithmetic."""
    def e(i, j):           # (R R_ref^T)[i][j] = row i of R . row j of R_ref
        return R[i][0] * R_ref[j][0] + R[i][1] * R_ref[j][1] + R[i][2] * R_ref[j][2]
    tr = e(0, 0) + e(1, 1) + e(2, 2)
    v = (e(2, 1) - e(1, 2), e(0, 2) - e(2, 0), e(1, 0) - e(0, 1))
    angle = math.acos(min(max((tr - 1.0) / 2.0, -1.0), 1.0))
    f = 0.5 if angle < 1e-8 else angle / (2.0 * math.sin(angle))
    return (f * v[0], f * v[1], f * v[2])


def unit(v: np.ndarray, name: str = "vector") -> np.ndarray:
    """v / |v|; ValueError naming `name` if v is (near) zero."""
    v = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise ValueError(f"{name}: expected a non-zero vector")
    return v / n


def signed_angle(a, b, axis) -> float:
    """Angle (rad) rotating a onto b about the unit `axis`, both projected on its normal plane.
    In plain floats (any 3-sequences): the simulated hinge calls it at 1 kHz."""
    ax, ay, az = (float(x) for x in axis)
    a0, a1, a2 = (float(x) for x in a)
    b0, b1, b2 = (float(x) for x in b)
    sa, sb = a0 * ax + a1 * ay + a2 * az, b0 * ax + b1 * ay + b2 * az
    a0, a1, a2 = a0 - sa * ax, a1 - sa * ay, a2 - sa * az
    b0, b1, b2 = b0 - sb * ax, b1 - sb * ay, b2 - sb * az
    c = (a1 * b2 - a2 * b1) * ax + (a2 * b0 - a0 * b2) * ay + (a0 * b1 - a1 * b0) * az
    return math.atan2(c, a0 * b0 + a1 * b1 + a2 * b2)


class Plane:
    """A plane of motion: unit `normal` and a right-handed in-plane basis (e1, e2 = n x e1).

    2D coordinates are taken relative to `origin`; the planar rate of a 3D
    angular velocity is its component along the normal, and in 2D
    w x r becomes w_n * J @ r with J = [[0, -1], [1, 0]].
    """

    J = np.array([[0.0, -1.0], [1.0, 0.0]])

    def __init__(self, normal: np.ndarray, origin: np.ndarray | None = None):
        n = unit(normal, "plane_normal")
        helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = unit(helper - np.dot(helper, n) * n)
        e2 = np.cross(n, e1)
        self.n = n
        self.E = np.vstack([e1, e2])            # (2, 3): world -> plane
        self.nnT = np.outer(n, n)
        self.origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=float).copy()

    def point2(self, p: np.ndarray) -> np.ndarray:
        """World point(s) (..., 3) to plane coordinates (..., 2) about the origin."""
        return (np.asarray(p) - self.origin) @ self.E.T

    def vec2(self, v: np.ndarray) -> np.ndarray:
        return np.asarray(v) @ self.E.T

    def lift(self, c2: np.ndarray) -> np.ndarray:
        """Plane point (2,) to the world point in the plane through the origin."""
        return self.origin + c2 @ self.E

    def lift_cov(self, P2: np.ndarray, along_var: float) -> np.ndarray:
        """In-plane covariance (2, 2) to world (3, 3), with `along_var` along the normal."""
        return self.E.T @ P2 @ self.E + along_var * self.nnT
