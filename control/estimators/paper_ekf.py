"""`paper-ekf`: the paper's EKF as published (TECDAR, Sec. III-C), the reference for every improvement."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tecdard.control.estimators.base import CONSISTENCY_TAU_S, UNOBSERVED_STD_M, ContactEstimator, EstimatorSpec
from tecdard.control.geometry import Plane, rotvec_to_matrix, skew
from tecdard.control.measurements import Samples
from tecdard.options import option, read_options


@dataclass
class PaperEkfParams:
    """The `estimator.paper_ekf` section: the paper's published tuning (Sec. III-C), per filter step; P[0] is
    not published (ours)."""
    q_p: float = option(1e-4, "the paper's alpha_p: process noise of the TCP position", minval=0.0)
    q_v: float = option(1e-3, "the paper's alpha_q: process noise of the TCP velocity", minval=0.0)
    q_c: float = option(1e-12, "the paper's alpha_c: process noise of the contact", minval=0.0)
    m_p: float = option(1e-5, "the paper's beta_p: position measurement noise", above=0.0)
    m_v: float = option(1e-5, "the paper's beta_v: velocity measurement noise", above=0.0)
    p0_c: float = option(UNOBSERVED_STD_M ** 2, "the contact's prior variance (ours: the paper gives none)",
                         unit="m^2", above=0.0)

    @classmethod
    def from_config(cls, section) -> "PaperEkfParams":
        return read_options(cls, section)


class PaperEKF(ContactEstimator):
    """`paper-ekf`: the paper's filter as published, the reference for every improvement.

    State x = [p_g, v_g, p_c] (3D: 9, planar: 6). Prediction: p_g += dt v_g,
    v_g rotated by R(w dt), p_c constant, plus Q = diag(q_p, q_v, q_c).
    Observation z = [p_g, v_g] with h(x) = [p_g, w x (p_g - p_c)] and
    M = diag(m_p, m_v), one update per IMU sample.
    Where the paper is silent: P[0] = diag(m_p, m_v, p0_c); the paper's
    initial contact "0" is read as the TCP at onset (its simulation frame), not
    the robot base; w is the conditioned object rate that all methods share.
    """

    method = "paper-ekf"

    def __init__(self, params: PaperEkfParams | None = None, plane: Plane | None = None):
        self.params = params or PaperEkfParams()
        self.plane = plane
        self.d = 2 if plane is not None else 3
        d, p = self.d, self.params
        n = 3 * d
        self.Q = np.diag([p.q_p] * d + [p.q_v] * d + [p.q_c] * d)
        self.M = np.diag([p.m_p] * d + [p.m_v] * d)
        self.x = np.zeros(n)
        self.P = np.eye(n)
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self.y = np.zeros(2 * d)
        self.nis = 0.0
        self.consistency = 1.0     # NIS / its expectation, smoothed over CONSISTENCY_TAU_S
        self.steps = 0
        self.rejected = 0
        self._F = np.eye(n)
        self._H = np.zeros((2 * d, n))
        self._H[:d, :d] = np.eye(d)
        self._I = np.eye(n)
        self.origin = np.zeros(3)

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        d, p = self.d, self.params
        self.origin = np.asarray(p_g, dtype=float).copy()
        if self.plane is not None:
            self.plane.origin = self.origin
            v2 = self.plane.vec2(v_g)
            self.x[:] = np.concatenate([np.zeros(2), v2, np.zeros(2)])
        else:
            self.x[:] = np.concatenate([p_g, v_g, p_g])
        self.P = np.diag([p.m_p] * d + [p.m_v] * d + [p.p0_c] * d)
        self.steps = 0
        self.rejected = 0
        self.consistency = 1.0

    def _step(self, dt: float, w: np.ndarray, z_p: np.ndarray, z_v: np.ndarray) -> None:
        d = self.d
        F, H = self._F, self._H
        F[0:d, d:2 * d] = dt * np.eye(d)
        if d == 3:
            F[3:6, 3:6] = rotvec_to_matrix(w * dt)
            W = skew(w)
        else:
            c, s = np.cos(w * dt), np.sin(w * dt)
            F[2:4, 2:4] = [[c, -s], [s, c]]
            W = w * Plane.J
        x = F @ self.x
        P = F @ self.P @ F.T + self.Q
        self.x_prior, self.P_prior = x, P
        H[d:, 0:d] = W
        H[d:, 2 * d:] = -W
        h = np.concatenate([x[0:d], W @ (x[0:d] - x[2 * d:])])
        y = np.concatenate([z_p, z_v]) - h
        PHt = P @ H.T
        S = H @ PHt + self.M
        self.y = y
        self.nis = float(y @ np.linalg.solve(S, y))
        self.consistency += min(dt / CONSISTENCY_TAU_S, 1.0) * (self.nis / (2 * d) - self.consistency)
        K = np.linalg.solve(S, PHt.T).T
        self.x = x + K @ y
        # Joseph form keeps P symmetric positive definite through thousands of steps a second.
        A = self._I - K @ H
        self.P = A @ P @ A.T + K @ self.M @ K.T
        self.steps += 1

    def update(self, samples: Samples) -> None:
        """Per-sample updates over a run: dt, w, p and v of each sample. The rest of the record is unused
        (fixed M, eta as scheduled, v as of each sample, as published)."""
        dt, w, p, v = samples.dt, samples.w, samples.p, samples.v
        if self.plane is not None:
            w_n = w @ self.plane.n
            p2 = self.plane.point2(p)
            v2 = self.plane.vec2(v)
            for k in range(len(dt)):
                self._step(float(dt[k]), float(w_n[k]), p2[k], v2[k])
        else:
            for k in range(len(dt)):
                self._step(float(dt[k]), w[k], p[k], v[k])

    def covariance(self) -> np.ndarray:
        d = self.d
        Pc = self.P[2 * d:, 2 * d:]
        return self.plane.lift_cov(Pc, UNOBSERVED_STD_M ** 2) if self.plane is not None else Pc.copy()

    def report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c, reported covariance, statistical covariance), world."""
        cov = self.covariance()
        d = self.d
        p_c = self.plane.lift(self.x[2 * d:]) if self.plane is not None else self.x[6:9].copy()
        return p_c, cov, cov


ESTIMATORS = (EstimatorSpec("paper-ekf", "the paper's EKF as published",
                            lambda options, plane: PaperEKF(options, plane), "paper_ekf", PaperEkfParams),)
