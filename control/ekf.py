"""Differential-constraint EKF for extrinsic contact: v_tcp = w x (p_tcp - p_c) (paper, Sec. III-C)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from control.geometry import rotvec_to_matrix

_I3 = np.eye(3)
_I9 = np.eye(9)


@dataclass
class EkfParams:
    """Noise model, variances in SI units (per filter step for Q).

    The defaults are the paper's published values (alpha_p, alpha_q, alpha_c,
    beta_p, beta_v); the paper does not publish P[0], so the initial variances
    here are ours: TCP state from the measurement noise, contact 0.5 m a side.
    """
    q_p: float = 1e-4      # alpha_p, TCP position process noise, m^2
    q_v: float = 1e-3      # alpha_q, TCP velocity process noise, (m/s)^2
    q_c: float = 1e-12     # alpha_c, contact point random walk, m^2
    m_p: float = 1e-5      # beta_p, TCP position measurement noise, m^2
    m_v: float = 1e-5      # beta_v, differential-constraint velocity noise, (m/s)^2
    p0_c: float = 0.25     # initial contact variance, m^2
    gate_nis: float = 0.0  # reject updates whose NIS exceeds this (0: no gating)

    @classmethod
    def from_config(cls, section) -> "EkfParams":
        d = cls()
        return cls(
            q_p=section.getfloat("q_p", d.q_p, minval=0.0),
            q_v=section.getfloat("q_v", d.q_v, minval=0.0),
            q_c=section.getfloat("q_c", d.q_c, minval=0.0),
            m_p=section.getfloat("m_p", d.m_p, above=0.0),
            m_v=section.getfloat("m_v", d.m_v, above=0.0),
            p0_c=section.getfloat("p0_c", d.p0_c, above=0.0),
            gate_nis=section.getfloat("gate_nis", d.gate_nis, minval=0.0),
        )


class ContactEKF:
    """State x = [p_g, v_g, p_c] (world, m and m/s); measurement z = [p_g, v_g] from proprioception.

    Prediction integrates the TCP and rotates its velocity by the measured
    rotation w*dt; the observation is h(x) = [p_g, w x (p_g - p_c)], so the
    contact point is corrected through the velocity residual. The angular rate
    w is an input (the conditioned object rate), which makes the model linear
    in the state for a given w: H is exact, not a linearisation.
    """

    def __init__(self, params: EkfParams | None = None):
        self.params = params or EkfParams()
        p = self.params
        self.Q = np.diag([p.q_p] * 3 + [p.q_v] * 3 + [p.q_c] * 3)
        self.M = np.diag([p.m_p] * 3 + [p.m_v] * 3)
        self.x = np.zeros(9)
        self.P = np.eye(9)
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()
        self.y = np.zeros(6)
        self.nis = 0.0
        self.steps = 0
        self.rejected = 0
        self._F = np.eye(9)
        self._H = np.zeros((6, 9))
        self._H[0:3, 0:3] = _I3

    def start(self, p_g: np.ndarray, v_g: np.ndarray, p_c0: np.ndarray | None = None) -> None:
        """Initialise at contact onset: TCP state from proprioception, contact at p_c0 (default: the TCP)."""
        p = self.params
        self.x[0:3] = p_g
        self.x[3:6] = v_g
        self.x[6:9] = p_g if p_c0 is None else p_c0
        self.P = np.diag([p.m_p] * 3 + [p.m_v] * 3 + [p.p0_c] * 3)
        self.steps = 0
        self.rejected = 0

    @property
    def p_c(self) -> np.ndarray:
        return self.x[6:9]

    @property
    def std_c(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.P)[6:9], 0.0))

    def step(self, dt: float, w: np.ndarray, z_p: np.ndarray, z_v: np.ndarray) -> float:
        """One predict/update at time step dt (s) with object rate w (rad/s, world); returns the NIS."""
        F = self._F
        F[0:3, 3:6] = dt * _I3
        F[3:6, 3:6] = rotvec_to_matrix(w * dt)
        x = F @ self.x
        P = F @ self.P @ F.T + self.Q
        self.x_prior, self.P_prior = x, P

        W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        H = self._H
        H[3:6, 0:3] = W
        H[3:6, 6:9] = -W
        h = np.concatenate([x[0:3], W @ (x[0:3] - x[6:9])])
        y = np.concatenate([z_p, z_v]) - h
        PHt = P @ H.T
        S = H @ PHt + self.M
        Sinv_y = np.linalg.solve(S, y)
        nis = float(y @ Sinv_y)
        self.y, self.nis = y, nis
        self.steps += 1
        if self.params.gate_nis > 0 and nis > self.params.gate_nis and self.steps > 1:
            self.rejected += 1
            self.x, self.P = x, P
            return nis
        K = np.linalg.solve(S, PHt.T).T
        self.x = x + K @ y
        # Joseph form keeps P symmetric positive definite despite rounding at 7 kHz.
        A = _I9 - K @ H
        self.P = A @ P @ A.T + K @ self.M @ K.T
        return nis
