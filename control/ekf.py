"""Contact filters on the differential constraint v_tcp = w x (p_tcp - p_c): the paper's EKF and ours.

Both take, per IMU sample, the time step, the object's angular rate `w`
(world, conditioned: bias-free, filtered, eta-scaled) and the TCP position and
velocity from proprioception (world, causal), and estimate the contact point
p_c. With `plane` given they work in that plane (2D), otherwise in 3D. Along
a line contact (or the hinge axis) p_c is unobservable: the estimate keeps the
TCP's coordinate at onset there and the reported one-sigma stays large.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from control.geometry import Plane, rotvec_to_matrix, sym2_max_eig

UNOBSERVED_STD_M = 0.5     # one-sigma reported along an unobservable direction
CONSISTENCY_TAU_S = 0.05   # smoothing of the NIS ratio (innovation consistency)


@dataclass
class PaperEkfParams:
    """The paper's published tuning (Sec. III-C), per filter step; P[0] is not published (ours)."""
    q_p: float = 1e-4      # alpha_p
    q_v: float = 1e-3      # alpha_q
    q_c: float = 1e-12     # alpha_c
    m_p: float = 1e-5      # beta_p
    m_v: float = 1e-5      # beta_v
    p0_c: float = UNOBSERVED_STD_M ** 2

    @classmethod
    def from_config(cls, section) -> "PaperEkfParams":
        d = cls()
        return cls(
            q_p=section.getfloat("q_p", d.q_p, minval=0.0),
            q_v=section.getfloat("q_v", d.q_v, minval=0.0),
            q_c=section.getfloat("q_c", d.q_c, minval=0.0),
            m_p=section.getfloat("m_p", d.m_p, above=0.0),
            m_v=section.getfloat("m_v", d.m_v, above=0.0),
            p0_c=section.getfloat("p0_c", d.p0_c, above=0.0),
        )


class PaperEKF:
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
            W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
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

    def update(self, dt: np.ndarray, w: np.ndarray, p: np.ndarray, v: np.ndarray,
               var_v: np.ndarray | None = None, var_w: np.ndarray | None = None,
               fresh: np.ndarray | None = None) -> None:
        """Per-sample updates over a chunk: dt (n,), w/p/v (n, 3) world. var_v/var_w/fresh unused (fixed M)."""
        if self.plane is not None:
            w_n = w @ self.plane.n
            p2 = self.plane.point2(p)
            v2 = self.plane.vec2(v)
            for k in range(len(dt)):
                self._step(float(dt[k]), float(w_n[k]), p2[k], v2[k])
        else:
            for k in range(len(dt)):
                self._step(float(dt[k]), w[k], p[k], v[k])

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(p_c, one-sigma per world axis), m."""
        d = self.d
        Pc = self.P[2 * d:, 2 * d:]
        if self.plane is not None:
            cov = self.plane.lift_cov(Pc, UNOBSERVED_STD_M ** 2)
            return self.plane.lift(self.x[2 * d:]), np.sqrt(np.diag(cov))
        return self.x[6:9].copy(), np.sqrt(np.maximum(np.diag(Pc), 0.0))

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


@dataclass
class ContactKfParams:
    """Noise model of our filter, SI units; variances per sample unless stated."""
    sigma_w: float = 0.01          # rad/s, per-sample object-rate noise (raw gyro noise x eta)
    sigma_p: float = 5e-5          # m, TCP position noise (encoder grade)
    sigma_v: float = 1e-3          # m/s, reported TCP velocity noise
    q_c: float = 1e-8              # m^2/s, contact random walk
    p0_c: float = UNOBSERVED_STD_M ** 2
    gate_nis: float = 16.3         # chi^2 (3 dof) at 0.999; 0 disables gating
    eta_rel_std: float = 0.05      # relative uncertainty of eta, reported as a radial floor
    max_block: int = 64            # samples per collapsed update
    use_positions: bool = True     # TCP positions as evidence too (rigid-body displacement), see PositionEvidence

    @classmethod
    def from_config(cls, section) -> "ContactKfParams":
        d = cls()
        return cls(
            sigma_w=section.getfloat("sigma_w", d.sigma_w, above=0.0),
            sigma_p=section.getfloat("sigma_p", d.sigma_p, minval=0.0),
            sigma_v=section.getfloat("sigma_v", d.sigma_v, above=0.0),
            q_c=section.getfloat("q_c", d.q_c, minval=0.0),
            p0_c=section.getfloat("p0_c", d.p0_c, above=0.0),
            gate_nis=section.getfloat("gate_nis", d.gate_nis, minval=0.0),
            eta_rel_std=section.getfloat("eta_rel_std", d.eta_rel_std, minval=0.0, maxval=1.0),
            max_block=section.getint("max_block", d.max_block, minval=1, maxval=4096),
            use_positions=section.getbool("use_positions", d.use_positions),
        )


GATE_HPH_RATIO = 0.1           # NIS gating starts once H P H^T is this small against R


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs ~10x more on small arrays)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _cross_cov(a: np.ndarray) -> np.ndarray:
    """[a]x [a]x^T = |a|^2 I - a a^T for rows of a (n, 3) -> (n, 3, 3)."""
    out = -(a[:, :, None] * a[:, None, :])
    sq = (a * a).sum(axis=1)
    out[:, 0, 0] += sq
    out[:, 1, 1] += sq
    out[:, 2, 2] += sq
    return out


MIN_RESIDUAL_SAMPLES = 8       # position samples before the rigid-body residual test can speak
POSITION_RESIDUAL_LIMIT = 4.0  # residual / expectation above which positions are no evidence (slide)


class PositionEvidence:
    """What the TCP's measured positions say about the contact beyond its velocities.

    Integrating v = w x (r - c) from a reference time: r(t) - G(t) = q - Theta(t) x c,
    with Theta = int w dt, G = int w x r dt (r: the TCP relative to the onset TCP) and
    q the true TCP at the reference time, unknown. Each proprioception sample is then a
    linear measurement of (c, q) with its own independent noise sigma_p. q is
    marginalised in closed form (a regression on Theta with an intercept), so the
    marginal information on c is a Schur complement of running sums; it only grows, and
    each growth is handed to the filter as one exactly equivalent measurement. Reported
    velocities and positions carry independent noise, so nothing is counted twice (the
    gyro noise both share is small against either and is neglected).

    Planar: Theta is the scalar angle and Theta x c is theta J c.

    The regression's residual checks the rigid-body model: when the TCP moves relative
    to the object (sliding in the grasp during a translational probe or an ongoing
    motion) displacements integrate that motion without bound, the residual grows far
    beyond the position noise, and the evidence is switched off for the episode.
    """

    def __init__(self, d: int, sigma_p: float):
        self.d = d
        self.var = max(sigma_p, 1e-7) ** 2
        self.reset()
        self.broken = False

    def start(self) -> None:
        self.reset()
        self.broken = False

    def reset(self) -> None:
        d = self.d
        self.theta = 0.0 if d == 2 else np.zeros(3)
        self.g = np.zeros(d)
        self.n = 0
        self.s_th = 0.0 if d == 2 else np.zeros(3)
        self.s_hh = 0.0 if d == 2 else np.zeros((3, 3))
        self.s_y = np.zeros(d)
        self.s_yy = 0.0
        self.s_hy = np.zeros(d)
        self.lam = np.zeros((d, d))
        self.eta = np.zeros(d)

    def add(self, dt: np.ndarray, w: np.ndarray, r: np.ndarray, fresh: np.ndarray) -> bool:
        """Integrate a chunk (w: (n,) in-plane rate or (n, 3); r: (n, d)) and take the positions
        at the `fresh` samples (a new proprioception sample); True when any was taken."""
        idx = np.flatnonzero(fresh)
        if self.d == 2:
            return self._add_planar(w * dt, r, idx)
        wdt = w * dt[:, None]
        if len(idx) == 0:
            self.theta = self.theta + wdt.sum(axis=0)
            self.g = self.g + cross_rows(wdt, r).sum(axis=0)
            return False
        th = self.theta + np.cumsum(wdt, axis=0)
        g = self.g + np.cumsum(cross_rows(wdt, r), axis=0)
        self.theta, self.g = th[-1], g[-1]
        t_k, y_k = th[idx], r[idx] - g[idx]
        self.n += len(idx)
        self.s_yy += float((y_k * y_k).sum())
        sq = (t_k * t_k).sum(axis=1)
        self.s_th += t_k.sum(axis=0)
        self.s_hh += sq.sum() * np.eye(3) - t_k.T @ t_k
        self.s_y += y_k.sum(axis=0)
        self.s_hy += cross_rows(t_k, y_k).sum(axis=0)
        return True

    def _add_planar(self, wdt: np.ndarray, r: np.ndarray, idx: np.ndarray) -> bool:
        """The planar chunk in plain floats: a chunk holds a few proprioception samples at most."""
        rx, ry = r[:, 0], r[:, 1]
        th, gx, gy = self.theta, float(self.g[0]), float(self.g[1])
        k0 = 0
        for k in idx.tolist():
            seg = wdt[k0:k + 1]
            th += float(seg.sum())
            gx -= float(seg @ ry[k0:k + 1])
            gy += float(seg @ rx[k0:k + 1])
            k0 = k + 1
            yx, yy = float(rx[k]) - gx, float(ry[k]) - gy
            self.n += 1
            self.s_yy += yx * yx + yy * yy
            self.s_th += th
            self.s_hh += th * th
            self.s_y[0] += yx
            self.s_y[1] += yy
            self.s_hy[0] += th * yx
            self.s_hy[1] += th * yy
        seg = wdt[k0:]
        if len(seg):
            th += float(seg.sum())
            gx -= float(seg @ ry[k0:])
            gy += float(seg @ rx[k0:])
        self.theta = th
        self.g[0], self.g[1] = gx, gy
        return len(idx) > 0

    def increment(self) -> tuple[np.ndarray, np.ndarray]:
        """(dLambda, deta): the growth of the marginal information on c since the last call."""
        n = max(self.n, 1)
        if self.d == 2:
            l_u = (self.s_hh - self.s_th * self.s_th / n) / self.var
            lam = np.array([[l_u, 0.0], [0.0, l_u]])
            v = self.s_hy - self.s_th * self.s_y / n
            eta = np.array([-v[1], v[0]]) / self.var             # J v
        else:
            st = self.s_th
            lam = (self.s_hh - ((st @ st) * np.eye(3) - np.outer(st, st)) / n) / self.var
            eta = (self.s_hy - np.cross(st, self.s_y) / n) / self.var
        d_lam, d_eta = lam - self.lam, eta - self.eta
        self.lam, self.eta = lam, eta
        return 0.5 * (d_lam + d_lam.T), d_eta

    def residual_ratio(self) -> float:
        """Least-squares residual of the (c, q) regression over its expectation (1 when the model holds)."""
        n = self.n
        if n < MIN_RESIDUAL_SAMPLES:
            return 1.0
        lam_u, eta_u = self.lam * self.var, self.eta * self.var
        if self.d == 2:          # isotropic: lam_u = l I
            l_u = float(lam_u[0, 0])
            rank = 2 if l_u > 0.0 else 0
            fit = float(eta_u @ eta_u) / l_u if rank else 0.0
        else:
            ev = np.linalg.eigvalsh(lam_u)
            good = ev > 1e-9 * max(float(ev[-1]), 1e-300)
            rank = int(np.count_nonzero(good))
            fit = float(eta_u @ np.linalg.lstsq(lam_u, eta_u, rcond=1e-9)[0]) if rank else 0.0
        dof = self.d * n - self.d - rank
        if dof <= 0:
            return 1.0
        rss = self.s_yy - float(self.s_y @ self.s_y) / n - fit
        return max(rss, 0.0) / (self.var * dof)


class ContactKF:
    """`ekf`: our filter on the same constraint, built for accuracy, honesty and speed.

    Levers (see docs/estimation.md):
    - The state is the contact point alone. The TCP position and velocity are
      measured inputs (reported `tcp_vel` when the robot gives it) whose noise
      enters the measurement model, instead of states driven by large process
      noise. Given w the model is linear, so H is exact.
    - A consistent measurement noise per sample: velocity noise including the
      staleness of causal proprioception, gyro noise through [r]x and position
      noise through [w]x, inflated by the number of IMU samples that share one
      proprioception sample (their errors are one error, not many).
    - Onset initialisation from the first block by an iterated update, and
      NIS gating of outliers.
    - Updates collapse each block of samples into one exactly equivalent
      measurement (H_eq^T H_eq = sum H^T R^-1 H), applied in Joseph form: per
      sample work is vectorised.
    - The reported covariance adds the radial effect of eta's uncertainty, a
      systematic error no amount of averaging removes.
    """

    method = "ekf"

    def __init__(self, params: ContactKfParams | None = None, plane: Plane | None = None):
        self.params = params or ContactKfParams()
        self.plane = plane
        self.d = 2 if plane is not None else 3
        self.c = np.zeros(self.d)        # contact relative to the TCP at onset (plane coords if planar)
        self.P = np.eye(self.d)
        self.origin = np.zeros(3)
        self.corr_samples = 1.0          # IMU samples per proprioception sample
        self.eta_rel_std = self.params.eta_rel_std   # the pipeline raises it away from eta's calibration
        self.consistency = 1.0           # smoothed block NIS / its expectation (>= 1 scales the report)
        # Extra variance, (m/s)^2, of the TCP velocity along the lever arm. Set while a controller
        # follows an arc about the estimate: its own path error then moves the TCP along the lever
        # arm, the compliant grasp absorbs it, and that component is no evidence about the contact.
        # The tangential component (|v| = w |r|) stays, and the turning lever arm triangulates.
        self.radial_var = 0.0
        self.steps = 0
        self.rejected = 0
        self.nis = 0.0
        self._r_last = np.zeros(self.d)
        self._planar_chunk = (np.zeros(0), np.zeros((0, 2)))
        self.positions = PositionEvidence(self.d, self.params.sigma_p) if self.params.use_positions else None

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        self.origin = np.asarray(p_g, dtype=float).copy()
        if self.plane is not None:
            self.plane.origin = self.origin
        if self.positions is not None:
            self.positions.start()
        self.c = np.zeros(self.d)
        self.P = self.params.p0_c * np.eye(self.d)
        self.steps = 0
        self.rejected = 0
        self.consistency = 1.0

    def update(self, dt: np.ndarray, w: np.ndarray, p: np.ndarray, v: np.ndarray,
               var_v: np.ndarray | None = None, var_w: np.ndarray | None = None,
               fresh: np.ndarray | None = None) -> None:
        """Chunk of samples: dt (n,), w/p/v (n, 3) world; var_v (m/s)^2 and var_w (rad/s)^2 are
        per-sample extra variances of the velocity and the object rate (staleness); `fresh`
        (n,) bool marks the samples whose p is a new proprioception sample (PositionEvidence)."""
        n = len(dt)
        if var_v is None:
            var_v = np.full(n, self.params.sigma_v ** 2)
        if var_w is None:
            var_w = np.zeros(n)
        mb = self.params.max_block
        for k0 in range(0, n, mb):
            sl = slice(k0, k0 + mb)
            # At onset the noise model is linearised about a guess; iterate once on the
            # first block (from the same prior) so it is linearised about the data's answer.
            c_lin = self.c
            for _ in range(2 if self.steps == 0 else 0):
                c_lin = self._block(float(np.sum(dt[sl])), w[sl], p[sl], v[sl], var_v[sl], var_w[sl], c_lin,
                                    commit=False)
            self._block(float(np.sum(dt[sl])), w[sl], p[sl], v[sl], var_v[sl], var_w[sl], c_lin, commit=True)
            if self.positions is not None:
                if fresh is None:
                    self.positions.reset()     # no position measurements here: restart the reference
                else:
                    self._position_update(dt[sl], w[sl], p[sl], fresh[sl])

    def _position_update(self, dt, w, p, fresh) -> None:
        ev = self.positions
        if ev.broken:
            return
        if self.radial_var > 0:
            # Following an arc: the grasp's compliance moves the TCP along the lever arm, which a
            # displacement integrates without bound. Restart the reference instead of using it.
            ev.reset()
            return
        if self.plane is not None:
            w_n, r0 = self._planar_chunk
            taken = ev.add(dt, w_n, r0, fresh)
        else:
            taken = ev.add(dt, w, p - self.origin, fresh)
        if not taken:
            return
        d_lam, d_eta = ev.increment()
        if ev.residual_ratio() > POSITION_RESIDUAL_LIMIT:
            ev.broken = True        # the TCP moves relative to the object: displacements mislead
            return
        b = d_eta - d_lam @ self.c
        if self.plane is not None:
            self._commit_planar(self.P, d_lam, b, 0, None, None, None, 0.0, True, consistency=False)
        else:
            self._commit_general(self.P, d_lam, b, 0, None, None, None, 0.0, True, consistency=False)

    def _block(self, duration: float, w, p, v, var_v, var_w, c_lin: np.ndarray, commit: bool) -> np.ndarray:
        """One collapsed update from the current prior, noise linearised about c_lin; returns the posterior mean."""
        prm = self.params
        corr = max(self.corr_samples, 1.0)
        n = len(w)
        P = self.P + prm.q_c * duration * np.eye(self.d)
        if self.plane is not None:
            # In the plane R = a I + b u u^T + c rh rh^T with u = J r: gyro noise acts along the
            # tangent u, and `radial_var` (distrust of the velocity along the lever arm, see
            # below) along rh = r/|r|. R is diagonal in (rh, uh), so R^-1, sum H^T R^-1 H
            # (H = -w_n J) and the NIS are closed forms, element-wise over the block.
            # Per sample, in 1-D columns (x, y: plane coordinates); uh = J rh = (-rh_y, rh_x).
            w_n = w @ self.plane.n
            r0 = (p - self.origin) @ self.plane.E.T     # TCP relative to the onset TCP, plane coords
            if commit:
                self._planar_chunk = (w_n, r0)          # reused by the position evidence
            v2 = v @ self.plane.E.T
            r0x, r0y = r0[:, 0], r0[:, 1]
            yx = v2[:, 0] + w_n * (r0y - self.c[1])     # y = v - w_n J (r0 - c)
            yy = v2[:, 1] - w_n * (r0x - self.c[0])
            rx, ry = r0x - c_lin[0], r0y - c_lin[1]
            rr = rx * rx + ry * ry + 1e-18
            rn = np.sqrt(rr)
            a = corr * (var_v + prm.sigma_p ** 2 * w_n * w_n)
            inv_r = 1.0 / (a + corr * self.radial_var)           # along the lever arm
            inv_u = 1.0 / (a + (prm.sigma_w ** 2 + var_w) * rr)  # along the tangent
            yr = (rx * yx + ry * yy) / rn
            yu = (rx * yy - ry * yx) / rn
            gate = prm.gate_nis > 0 and self.steps > 0 and \
                float(np.mean(w_n * w_n)) * float(P[0, 0] + P[1, 1]) < GATE_HPH_RATIO * 2 * float(a.min())
            nis, keep = (yr * yr * inv_r + yu * yu * inv_u, None) if gate else (None, None)
            if gate:
                keep = nis <= prm.gate_nis
                if not keep.all():
                    w_n, rx, ry, rr, rn, inv_r, inv_u, yr, yu = (x[keep] for x in
                                                                 (w_n, rx, ry, rr, rn, inv_r, inv_u, yr, yu))
            al = w_n * w_n * inv_r / rr                 # weight of uh uh^T (J^T rh rh^T J)
            be = w_n * w_n * inv_u / rr                 # weight of rh rh^T (J^T uh uh^T J)
            sxx, syy, sxy = rx * rx, ry * ry, rx * ry
            a11 = float(np.dot(al, syy) + np.dot(be, sxx))
            a22 = float(np.dot(al, sxx) + np.dot(be, syy))
            a12 = float(np.dot(be - al, sxy))
            A = np.array([[a11, a12], [a12, a22]])
            # H^T R^-1 y = w_n (uh (rh.y) inv_r - rh (uh.y) inv_u)
            gr = w_n * yr * inv_r / rn
            gu = w_n * yu * inv_u / rn
            b = np.array([float(-np.dot(gr, ry) - np.dot(gu, rx)), float(np.dot(gr, rx) - np.dot(gu, ry))])
            return self._commit_planar(P, A, b, n, keep, nis, r0, duration, commit)
        else:
            r0 = p - self.origin
            z = v - cross_rows(w, r0)
            H = np.zeros((n, 3, 3))
            H[:, 0, 1], H[:, 0, 2] = w[:, 2], -w[:, 1]
            H[:, 1, 0], H[:, 1, 2] = -w[:, 2], w[:, 0]
            H[:, 2, 0], H[:, 2, 1] = w[:, 1], -w[:, 0]      # H = -[w]x
            y = z + cross_rows(w, np.broadcast_to(self.c, w.shape))
            r = r0 - c_lin
            R = (prm.sigma_w ** 2 + var_w)[:, None, None] * _cross_cov(r) \
                + (corr * prm.sigma_p ** 2) * _cross_cov(w)
            if self.radial_var > 0:
                rh = r / np.maximum(np.linalg.norm(r, axis=1), 1e-9)[:, None]
                R += (corr * self.radial_var) * (rh[:, :, None] * rh[:, None, :])
            iso = corr * var_v
            R[:, 0, 0] += iso
            R[:, 1, 1] += iso
            R[:, 2, 2] += iso
            Rinv = np.linalg.inv(R)
            HtRi = H.transpose(0, 2, 1) @ Rinv
            Hm = H.mean(axis=0)
            if prm.gate_nis > 0 and self.steps > 0 and np.trace(Hm @ P @ Hm.T) < GATE_HPH_RATIO * 3 * float(iso.min()):
                # Once converged H P H^T << R, so y^T R^-1 y is the NIS; gating before that would
                # reject the very samples that carry the information. (H removes the unobservable
                # direction along w, so a line contact's large along-edge variance does not count.)
                nis = np.einsum("ni,nij,nj->n", y, Rinv, y)
                keep = nis <= prm.gate_nis
            else:
                nis = None
                keep = None
            if keep is not None and not keep.all():
                HtRi, H, y = HtRi[keep], H[keep], y[keep]
            A = (HtRi @ H).sum(axis=0)
            b = (HtRi @ y[:, :, None]).sum(axis=0)[:, 0]
            return self._commit_general(P, A, b, n, keep, nis, r0, duration, commit)

    def _commit_general(self, P, A, b, n, keep, nis, r0, duration, commit, consistency: bool = True) -> np.ndarray:
        """The collapsed update for any dimension: H_eq from A's eigenvectors with data, unit noise, Joseph form."""
        lam, U = np.linalg.eigh(A)
        good = lam > 1e-12 * max(lam[-1], 1e-300)
        if commit:
            if keep is not None:
                self.rejected += int(n - np.count_nonzero(keep))
            if nis is not None and len(nis):
                self.nis = float(nis[-1])
        if not np.any(good):
            if commit:
                self.P = P
            return self.c
        sq = np.sqrt(lam[good])
        Ug = U[:, good]
        Heq = sq[:, None] * Ug.T                       # (r, d): Heq^T Heq = A
        yeq = (Ug.T @ b) / sq                           # Heq^T yeq = b
        HP = Heq @ P
        S_eq = HP @ Heq.T + np.eye(len(sq))
        K = np.linalg.solve(S_eq, HP).T
        c_new = self.c + K @ yeq
        if commit and consistency and self.steps > 0:
            # Block-level NIS of the collapsed measurement: chi^2 with len(sq) dof when the model
            # holds. A coherent bias (sliding in the grasp, a stale TCP rate) shows up here even
            # when each sample looks fine; its smoothed ratio scales the reported covariance.
            ratio = float(yeq @ np.linalg.solve(S_eq, yeq)) / len(sq)
            alpha = 1.0 - np.exp(-max(duration, 1e-4) / CONSISTENCY_TAU_S)
            self.consistency += alpha * (ratio - self.consistency)
        if commit:
            # Joseph form, with the collapsed measurement's unit noise.
            Aj = np.eye(self.d) - K @ Heq
            self.c, self.P = c_new, Aj @ P @ Aj.T + K @ K.T
            self.steps += n
            self._r_last = (r0[-1] - c_new) if n else self._r_last
        return c_new

    def _commit_planar(self, P, A, b, n, keep, nis, r0, duration, commit, consistency: bool = True) -> np.ndarray:
        """The collapsed 2 x 2 update in plain floats (numpy's per-call cost dominates at this size).

        Same algebra as the general path: H_eq from A (Cholesky when full rank, the principal
        eigenvector when rank one), unit measurement noise, Joseph-form covariance.
        """
        a11, a12, a22 = float(A[0, 0]), float(A[0, 1]), float(A[1, 1])
        b1, b2 = float(b[0]), float(b[1])
        p11, p12, p22 = float(P[0, 0]), float(P[0, 1]), float(P[1, 1])
        if commit:
            if keep is not None:
                self.rejected += int(n - np.count_nonzero(keep))
            if nis is not None and len(nis):
                self.nis = float(nis[-1])
        tr = a11 + a22
        det = a11 * a22 - a12 * a12
        if tr <= 0.0:
            if commit:
                self.P = P
            return self.c
        if det > 1e-12 * tr * tr and a11 > 0.0:
            # A = L L^T, H_eq = L^T (upper), y_eq = L^-1 b
            l11 = math.sqrt(a11)
            l21 = a12 / l11
            l22 = math.sqrt(max(a22 - l21 * l21, 1e-300))
            y1 = b1 / l11
            y2 = (b2 - l21 * y1) / l22
            # S = H P H^T + I with H = [[l11, l21], [0, l22]]
            hp11 = l11 * p11 + l21 * p12
            hp12 = l11 * p12 + l21 * p22
            hp21 = l22 * p12
            hp22 = l22 * p22
            s11 = hp11 * l11 + hp12 * l21 + 1.0
            s12 = hp12 * l22
            s22 = hp22 * l22 + 1.0
            sd = s11 * s22 - s12 * s12
            i11, i12, i22 = s22 / sd, -s12 / sd, s11 / sd
            # K = (H P)^T S^-1  (P symmetric)
            k11 = hp11 * i11 + hp21 * i12
            k12 = hp11 * i12 + hp21 * i22
            k21 = hp12 * i11 + hp22 * i12
            k22 = hp12 * i12 + hp22 * i22
            dc1 = k11 * y1 + k12 * y2
            dc2 = k21 * y1 + k22 * y2
            ratio = (y1 * (i11 * y1 + i12 * y2) + y2 * (i12 * y1 + i22 * y2)) / 2.0
            # I - K H
            m11 = 1.0 - k11 * l11
            m12 = -(k11 * l21 + k12 * l22)
            m21 = -k21 * l11
            m22 = 1.0 - (k21 * l21 + k22 * l22)
            kk11, kk12, kk22 = k11 * k11 + k12 * k12, k11 * k21 + k12 * k22, k21 * k21 + k22 * k22
        else:
            # rank one: H_eq = sqrt(lam) u^T, y_eq = u.b / sqrt(lam)
            lam = sym2_max_eig(a11, a12, a22)
            ux, uy = (a12, lam - a11) if abs(a12) > 1e-300 else ((1.0, 0.0) if a11 >= a22 else (0.0, 1.0))
            un = math.hypot(ux, uy)
            ux, uy = ux / un, uy / un
            sq = math.sqrt(lam)
            h1, h2 = sq * ux, sq * uy
            y1 = (ux * b1 + uy * b2) / sq
            ph1 = p11 * h1 + p12 * h2
            ph2 = p12 * h1 + p22 * h2
            s = h1 * ph1 + h2 * ph2 + 1.0
            k11, k21 = ph1 / s, ph2 / s
            dc1, dc2 = k11 * y1, k21 * y1
            ratio = y1 * y1 / s
            m11, m12, m21, m22 = 1.0 - k11 * h1, -k11 * h2, -k21 * h1, 1.0 - k21 * h2
            kk11, kk12, kk22 = k11 * k11, k11 * k21, k21 * k21
        c_new = self.c + np.array([dc1, dc2])
        if commit:
            if consistency and self.steps > 0:
                alpha = 1.0 - math.exp(-max(duration, 1e-4) / CONSISTENCY_TAU_S)
                self.consistency += alpha * (ratio - self.consistency)
            # Joseph form: M P M^T + K K^T
            mp11 = m11 * p11 + m12 * p12
            mp12 = m11 * p12 + m12 * p22
            mp21 = m21 * p11 + m22 * p12
            mp22 = m21 * p12 + m22 * p22
            n11 = mp11 * m11 + mp12 * m12 + kk11
            n12 = mp11 * m21 + mp12 * m22 + kk12
            n22 = mp21 * m21 + mp22 * m22 + kk22
            self.c = c_new
            self.P = np.array([[n11, n12], [n12, n22]])
            self.steps += n
            self._r_last = (r0[-1] - c_new) if n else self._r_last
        return c_new

    def _lift(self) -> tuple[np.ndarray, np.ndarray]:
        if self.plane is not None:
            return self.plane.lift(self.c), self.plane.lift_cov(self.P, UNOBSERVED_STD_M ** 2)
        return self.origin + self.c, self.P.copy()

    def report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c, reported covariance with the eta floor, the filter's own covariance), world."""
        p_c, stat = self._lift()
        stat = stat * max(self.consistency, 1.0)
        r = self._r_last
        r3 = r @ self.plane.E if self.plane is not None else r
        return p_c, stat + (self.eta_rel_std ** 2) * np.outer(r3, r3), stat

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        p_c, cov, _ = self.report()
        return p_c, np.sqrt(np.maximum(cov.diagonal(), 0.0))
