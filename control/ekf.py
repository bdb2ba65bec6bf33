"""Contact filters on the differential constraint v_tcp = w x (p_tcp - p_c): the paper's EKF and ours.

Both take, per IMU sample, the time step, the object's angular rate `w`
(world, conditioned: bias-free, filtered, eta-scaled) and the TCP position and
velocity from proprioception (world, causal), and estimate the contact point
p_c. With `plane` given they work in that plane (2D), otherwise in 3D. Along
a line contact (or the hinge axis) p_c is unobservable: the estimate keeps the
TCP's coordinate at onset there and the reported one-sigma stays large.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tecdard.control import kernels as kern
from tecdard.control.estimators import ContactEstimator, Snapshot
from tecdard.control.geometry import Plane, rotvec_to_matrix
from tecdard.control.kernels import (K_MIN, eta_evidence, eta_weight, position_increment, position_reset,
                                     position_residual, position_sums, report_state)

UNOBSERVED_STD_M = 0.5     # one-sigma reported along an unobservable direction
CONSISTENCY_TAU_S = 0.05   # smoothing of the NIS ratio (innovation consistency)
CONSISTENCY_WINDOW_S = 0.01  # the NIS ratio's window: at least the longest block (64 samples at 6.7 kHz)


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
               fresh: np.ndarray | None = None, w_tcp: np.ndarray | None = None, paired=None) -> None:
        """Per-sample updates over a chunk: dt (n,), w/p/v (n, 3) world. The rest is unused (fixed M, eta as
        scheduled, v as of each sample, as published)."""
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
    eta_rel_std: float = 0.05      # relative uncertainty of eta at its calibration (prior of the eta state)
    max_block: int = 64            # samples per collapsed update
    use_positions: bool = True     # TCP positions as evidence too (rigid-body displacement), see PositionEvidence
    estimate_eta: bool = True      # carry eta's error as a state, see ContactKF
    eta_test_sigma: float = 3.0    # the data must reject the calibrated eta by this many sigma to be used
    slip_radial_sigma: float = 0.005   # m/s, distrust of the velocity along the lever arm once positions show a slip
    arc_position_sigma: float = 0.001  # m, the TCP positions' noise while following an arc (0: no evidence then)

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
            estimate_eta=section.getbool("estimate_eta", d.estimate_eta),
            eta_test_sigma=section.getfloat("eta_test_sigma", d.eta_test_sigma, minval=0.0),
            slip_radial_sigma=section.getfloat("slip_radial_sigma", d.slip_radial_sigma, minval=0.0, maxval=1.0),
            arc_position_sigma=section.getfloat("arc_position_sigma", d.arc_position_sigma, minval=0.0, maxval=0.1),
        )


_IDENTITY = np.eye(3)
_NO_NORMAL = np.zeros(3)
_NO_ALONG = np.zeros(9)         # 3D: no variance added along a plane normal
_NO_FRESH = np.zeros(0, dtype=bool)


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs ~10x more on small arrays)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _position_var(sigma_p: float) -> float:
    """The position evidence's noise variance, m^2 (floored: a noise-free rig still has rounding)."""
    return max(sigma_p, 1e-7) ** 2


MIN_RESIDUAL_SAMPLES = 8       # position samples before the rigid-body residual test can speak
POSITION_RESIDUAL_LIMIT = 4.0  # residual / expectation above which positions are no evidence (slide)


class PositionEvidence:
    """What the TCP's measured positions say about the contact beyond its velocities.

    Integrating v = k w x (r - c) from a reference time (w: the object rate at the
    scheduled eta, k: the eta ratio, see ContactKF) gives
        r(t) = q + k G(t) - Theta(t) x m,    m = k c,
    with Theta = int w dt, G = int w x r dt (r: the TCP relative to the onset TCP) and
    q the true TCP at the reference time, unknown. Each proprioception sample is then a
    linear measurement of the filter's state (m, k) and of q, with its own independent
    noise sigma_p. q is marginalised in closed form (a regression with an intercept), so
    the marginal information on (m, k) is a Schur complement of running sums; it only
    grows, and each growth is handed to the filter as one exactly equivalent measurement.
    Reported velocities and positions carry independent noise, so nothing is counted
    twice (the gyro noise both share is small against either and is neglected). The
    k column is the curvature of the TCP's path against the gyro's angle: what tells a
    longer lever arm from a weaker fingertip once the object has turned a few degrees.

    Planar: Theta is the scalar angle and Theta x m is theta J m.

    A gripper that turns (w_tcp, its own rate) moves the TCP by w_tcp x (r - c) whatever
    eta is: with rel = w - w_tcp, v = w_tcp x r + k rel x r - rel x m - w_tcp x m / k, so
        r(t) - G_tcp(t) = q + k G(t) - Theta(t) x m,
    G_tcp = int w_tcp x r dt known, G = int rel x r dt and Theta = int (rel + w_tcp / k) dt,
    the 1/k linearised at the estimate. A gripper rate held between orientation samples
    lags while it changes; once it is steady the error it left is a constant, which the
    intercept q absorbs.

    The regression's residual checks the rigid-body model: when the TCP moves relative
    to the object (sliding in the grasp during a translational probe or an ongoing
    motion) displacements integrate that motion without bound, the residual grows far
    beyond the position noise, and the evidence is switched off for the episode.
    """

    def __init__(self, d: int, sigma_p: float, arc_sigma: float = 0.0):
        self.d = d
        nx = d + 1
        self.var = _position_var(sigma_p)
        self.arc_var = arc_sigma ** 2    # m^2, the noise of positions taken while following an arc
        # the state the compiled run updates (kernels.Evidence): the counts (kernels.EVIDENCE_STATUS),
        # the angle (planar) or rotation vector integrated, G, the gripper's own part of it, the regression's running sums (of the
        # regressors X_k (d x (d+1)), X_k^T X_k, X_k^T y_k, y_k), and the marginal information handed
        # over so far (Lambda, xi; eta is the transmission ratio)
        self.ev = kern.Evidence(kern.record(kern.EVIDENCE_STATUS), np.zeros(1 if d == 2 else 3), np.zeros(d),
                                np.zeros(d), np.zeros((d, nx)), np.zeros((nx, nx)), np.zeros(nx), np.zeros(d),
                                np.zeros((nx, nx)), np.zeros(nx))

    @property
    def n(self) -> int:
        """Position samples in the sums."""
        return int(self.ev.status[0]["n"])

    @property
    def s_yy(self) -> float:
        return float(self.ev.status[0]["s_yy"])

    @property
    def noise_var(self) -> float:
        """The noise variance of the positions in the sums: their own, or while following an arc the arc's."""
        return max(self.var, self.arc_var) if self.ev.status[0]["arc"] else self.var

    @property
    def broken(self) -> bool:
        """The rigid-body residual failed this episode: positions are no evidence until the next start."""
        return bool(self.ev.status[0]["broken"])

    def set_broken(self) -> None:
        self.ev.status[0]["broken"] = True

    def start(self) -> None:
        self.reset()
        self.ev.status[0]["broken"] = False
        self.ev.status[0]["arc"] = False

    def reset(self) -> None:
        """Restart the reference: no samples, integrals and sums zero (broken is kept)."""
        position_reset(self.ev)

    def add(self, dt: np.ndarray, w: np.ndarray, r: np.ndarray, fresh: np.ndarray, w_tcp: np.ndarray | None = None,
            k: float = 1.0) -> bool:
        """Integrate a chunk (w, and the gripper's own rate w_tcp: (n,) in-plane rates or (n, 3); r:
        (n, d)) and take the positions at the `fresh` samples (a new proprioception sample); True
        when any was taken. k: the eta ratio where the gripper's term is linearised."""
        ev = self.ev
        w = w.reshape(len(dt), -1)
        w_tcp = np.zeros(w.shape) if w_tcp is None else w_tcp.reshape(len(dt), -1)
        taken, s_yy = position_sums(ev.theta, ev.g, ev.g_tcp, dt, w, w_tcp, 1.0 / k, r, fresh, ev.s_x, ev.s_xx,
                                    ev.s_xy, ev.s_y)
        ev.status[0]["n"] += taken
        ev.status[0]["s_yy"] += s_yy
        return taken > 0

    def increment(self) -> tuple[np.ndarray, np.ndarray]:
        """(dLambda, dxi): the growth of the marginal information on (m, k) since the last call."""
        ev = self.ev
        return position_increment(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, self.n, self.noise_var, ev.lam, ev.xi)

    def residual_ratio(self, k: float = 1.0) -> float:
        """Least-squares residual of the (q, m) regression at the eta ratio k, over its expectation (1 when
        the model holds). k is held, not fitted: a free k would absorb part of a slip in the grasp."""
        ev = self.ev
        return position_residual(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, self.s_yy, self.n, self.noise_var, k,
                                 MIN_RESIDUAL_SAMPLES)


# the compiled run's position evidence for a filter without it (never read)
_NO_EVIDENCE = {d: PositionEvidence(d, 1.0).ev for d in (2, 3)}


class ContactKfSettings:
    """The pipeline's settings and inputs as `ekf` takes them (ContactKF, and
    control.reference.ReferenceKF): each hook of ContactEstimator kept as the state the next update
    or episode reads, and an update's optional inputs made whole."""

    params: ContactKfParams
    positions: "PositionEvidence | None"
    lag_aligned_positions = True     # update's w, p, w_tcp feed PositionEvidence alone (ContactEstimator)

    def set_arc_radial_var(self, var_m2_s2: float) -> None:
        self.radial_var = var_m2_s2

    def set_eta_prior(self, mean: float, rel_std: float) -> None:
        self.eta_prior_mean, self.eta_rel_std = mean, rel_std

    def set_correlation(self, samples: float) -> None:
        self.corr_samples = samples

    def set_position_noise(self, sigma_m: float) -> None:
        self.sigma_p = max(float(sigma_m), self.params.sigma_p)
        if self.positions is not None:
            self.positions.var = _position_var(self.sigma_p)

    def radial_var_now(self) -> float:
        """The distrust of the velocity along the lever arm, (m/s)^2: the arc follower's, or once the
        positions have shown the TCP moving relative to the object (PositionEvidence.broken: a
        push that stretches the grasp, a slide), the slip's. The slip runs along the lever arm, and
        taken as evidence it turned the estimate (MuJoCo pushes: 7-12 mm off at the end; 4-5 mm
        with it)."""
        if self.positions is not None and self.positions.broken:
            return max(self.radial_var, self.params.slip_radial_sigma ** 2)
        return self.radial_var

    def _episode_prior(self, p_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A new episode from the TCP at onset p_g: the origin (and the plane's), the position
        evidence restarted, eta's prior read from the settings; returns the state's prior (x, P):
        the contact at the onset TCP, k at its prior mean."""
        d = self.d
        self.origin = np.asarray(p_g, dtype=float).copy()
        if self.plane is not None:
            self.plane.origin = self.origin
        if self.positions is not None:
            self.positions.start()
        self.k_prior_mean = self.eta_prior_mean
        self.k_prior_var = self.eta_rel_std ** 2 if self.nk else 0.0
        x = np.append(np.zeros(d), [self.k_prior_mean] * self.nk)
        return x, np.diag([self.params.p0_c] * d + [self.k_prior_var] * self.nk)

    def _inputs(self, n: int, w, p, var_v, var_w, w_tcp, paired):
        """(var_v, var_w, w_tcp, w_v, w_tcp_v, p_v) for n samples (ContactKF.update's arguments)."""
        var_v = np.full(n, self.params.sigma_v ** 2) if var_v is None else var_v
        var_w = np.zeros(n) if var_w is None else var_w
        w_tcp = np.zeros((n, 3)) if w_tcp is None else w_tcp
        if paired is None:
            return var_v, var_w, w_tcp, w, w_tcp, p
        w_v, w_tcp_v, p_v, n_avg = paired
        # the paired rate averages n_avg samples' noise, and every sample holding this velocity
        # repeats it: one error, shared like the velocity's (corr)
        var_w = var_w + self.params.sigma_w ** 2 * (max(self.corr_samples, 1.0) / n_avg - 1.0)
        return var_v, var_w, w_tcp, w_v, w_tcp_v, p_v


class ContactKF(ContactKfSettings, ContactEstimator):
    """`ekf`: our filter on the same constraint, built for accuracy, honesty and speed.

    State x = [m, k]: k = eta_true / eta_used is the error of the scheduled eta and
    m = k c, with c the contact relative to the TCP at onset (plane coordinates when
    planar). The object's true rate is w_tcp + k (w - w_tcp) for the rate w computed
    with the scheduled eta, so with the gripper still
        v = k w x r0 - w x m
    is linear in the state (r0: the TCP relative to its onset position); a turning
    gripper adds w_tcp x (r0 - m / k), linearised about the estimate.

    Levers (see docs/estimation.md):
    - The TCP position and velocity are measured inputs (reported `tcp_vel` when the
      robot gives it) whose noise enters the measurement model, instead of states
      driven by large process noise.
    - A consistent measurement noise per sample: velocity noise including the
      staleness of causal proprioception, gyro noise through [r]x and position
      noise through [w]x, inflated by the number of IMU samples that share one
      proprioception sample (their errors are one error, not many).
    - Positions as evidence too (PositionEvidence).
    - Onset initialisation from the first block by an iterated update, and
      NIS gating of outliers.
    - Eta's error as a state with the calibration's uncertainty as its prior, leaning the
      way eta moves outside the calibrated grip forces (EtaSchedule.prior). The reported
      contact is the scheduled one (k at its prior mean, plus eta's uncertainty as a
      radial floor) until the data reject that by `eta_test_sigma`; then the free-eta
      estimate is blended in over kernels.ETA_BLEND_SIGMA, so the output does not jump.
    - Updates collapse each block of samples into one exactly equivalent
      measurement (H_eq^T H_eq = sum H^T R^-1 H), applied in Joseph form. A whole
      chunk of blocks, with the consistency window and the position evidence, is one
      compiled call (kernels.ekf_advance).
    """

    method = "ekf"

    def __init__(self, params: ContactKfParams | None = None, plane: Plane | None = None):
        self.params = params or ContactKfParams()
        self.sigma_p = self.params.sigma_p      # m, the TCP position noise this episode (set_position_noise)
        self.plane = plane
        self.d = d = 2 if plane is not None else 3
        # the report's variance along the plane's normal (unobservable), flattened for the kernel
        self._along_var = (UNOBSERVED_STD_M ** 2 * plane.nnT).ravel() if plane is not None else _NO_ALONG
        self._E = plane.E if plane is not None else _IDENTITY
        self._normal = plane.n if plane is not None else _NO_NORMAL
        self.nk = 1 if self.params.estimate_eta else 0   # k is a state, or held at its prior mean (cheaper)
        nx = d + self.nk
        self.x = np.zeros(nx)            # [m] or [m, k]
        self.P = np.eye(nx)
        self.origin = np.zeros(3)
        self.corr_samples = 1.0          # IMU samples per proprioception sample
        # eta's prior as the pipeline sets it from the grip force: the mean of k and its relative one-sigma
        # (raised away from eta's calibration, the mean moved off 1 outside the calibrated forces)
        self.eta_prior_mean = 1.0
        self.eta_rel_std = self.params.eta_rel_std
        self.k_prior_mean = 1.0          # as read at onset: k's prior, or the value k is held at
        self.k_prior_var = 0.0
        # Extra variance, (m/s)^2, of the TCP velocity along the lever arm. Set while a controller
        # follows an arc about the estimate: its own path error then moves the TCP along the lever
        # arm, the compliant grasp absorbs it, and that component is no evidence about the contact.
        # The tangential component (|v| = w |r|) stays, and the turning lever arm triangulates.
        self.radial_var = 0.0
        # The compiled run's state (kernels.ekf_advance): the counts and ratios (kernels.STATUS), the
        # lever arm at the last sample, and the consistency window: its start state and prior, its
        # information, and the per-sample NIS of its gated blocks.
        self._status = kern.record(kern.STATUS, consistency=1.0)
        self._r_last = np.zeros(d)
        self._win = kern.Window(np.zeros(nx), np.eye(nx), np.eye(nx), np.zeros(nx))
        self._gated = np.empty(256)
        self._prm = kern.record(kern.RUN_PARAMS)
        self._frame = kern.contiguous(kern.Frame(self._E, self._normal, self.origin))
        self.positions = PositionEvidence(d, self.params.sigma_p, self.params.arc_position_sigma) \
            if self.params.use_positions else None
        self._ev = self.positions.ev if self.positions is not None else _NO_EVIDENCE[d]

    @property
    def steps(self) -> int:
        """IMU samples taken this episode."""
        return int(self._status[0]["steps"])

    @property
    def rejected(self) -> int:
        """Samples the NIS gate rejected this episode."""
        return int(self._status[0]["rejected"])

    @property
    def nis(self) -> float:
        """The last gated sample's NIS."""
        return float(self._status[0]["nis"])

    @property
    def consistency(self) -> float:
        """The smoothed window NIS over its expectation (about 1 while the model holds; >= 1 scales the
        report, and the daemon's divergence stop reads it)."""
        return float(self._status[0]["consistency"])

    @property
    def k(self) -> float:
        """The eta ratio eta_true / eta_used, floored for division (its prior mean when not a state)."""
        return max(float(self.x[self.d]), K_MIN) if self.nk else self.k_prior_mean

    @property
    def c(self) -> np.ndarray:
        """The contact relative to the onset TCP with eta free (plane coordinates if planar), m."""
        return self.x[:self.d] / self.k

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        """Start an episode at the TCP state at onset; eta's prior is `eta_prior_mean`, `eta_rel_std` as set now."""
        self.x, self.P = self._episode_prior(p_g)
        self._status[0] = kern.record(kern.STATUS, consistency=1.0)[0]
        self._frame = kern.contiguous(kern.Frame(self._E, self._normal, self.origin))

    def update(self, dt: np.ndarray, w: np.ndarray, p: np.ndarray, v: np.ndarray,
               var_v: np.ndarray | None = None, var_w: np.ndarray | None = None,
               fresh: np.ndarray | None = None, w_tcp: np.ndarray | None = None, paired=None) -> None:
        """Chunk of samples: dt (n,), w/p/v (n, 3) world; var_v (m/s)^2 and var_w (rad/s)^2 are
        per-sample extra variances of the velocity and the object rate (staleness); `fresh`
        (n,) bool marks the samples whose p is a new proprioception sample (PositionEvidence);
        w_tcp (n, 3) is the gripper's own rate when it turns (None: still). `paired` = (w_v,
        w_tcp_v, p_v, n_avg): the object's rate, the gripper's and the TCP's position from when the
        held velocity v was measured, the rate a mean over n_avg (n,) IMU samples (None: v is
        taken as of each sample)."""
        samples = self._samples(dt, w, p, v, var_v, var_w, fresh, w_tcp, paired)
        self._gated = kern.ekf_advance(self.x, self.P, self._status, self._r_last, self._win, self._gated, self._ev,
                                       self.positions is not None, samples, 0, len(dt), fresh is not None,
                                       self._frame, self._run_params())

    def advance(self, ends, n_reports: int, dt, w, p, v, var_v, var_w, fresh, w_tcp=None,
                paired=None) -> list[Snapshot]:
        """ContactEstimator.advance in one compiled call (kernels.ekf_segments): the same segments
        and the same state after each as updates one by one, without their per-call cost."""
        samples = self._samples(dt, w, p, v, var_v, var_w, fresh, w_tcp, paired)
        nx, d = len(self.x), self.d
        out_x, out_P = np.empty((n_reports, nx)), np.empty((n_reports, nx, nx))
        out_r, out_s = np.empty((n_reports, d)), np.empty((n_reports, 3))
        self._gated = kern.ekf_segments(self.x, self.P, self._status, self._r_last, self._win, self._gated, self._ev,
                                        self.positions is not None, samples, fresh is not None, self._frame,
                                        self._run_params(), self.params.slip_radial_sigma ** 2,
                                        np.asarray(ends, dtype=np.int64), out_x, out_P, out_r, out_s)
        return [Snapshot(*self.report(out_x[j], out_P[j], out_s[j, 2], out_r[j]), int(out_s[j, 0]),
                         float(out_s[j, 1]), float(out_s[j, 2])) for j in range(n_reports)]

    def _samples(self, dt, w, p, v, var_v, var_w, fresh, w_tcp, paired):
        """update's arguments as the compiled run's Samples."""
        var_v, var_w, w_tcp, w_v, w_tcp_v, p_v = self._inputs(len(dt), w, p, var_v, var_w, w_tcp, paired)
        return kern.contiguous(kern.Samples(dt, w, w_tcp, p, v, w_v, w_tcp_v, p_v, var_v, var_w,
                                            _NO_FRESH if fresh is None else fresh))

    def _run_params(self) -> np.ndarray:
        """The compiled run's parameters (kernels.RUN_PARAMS) as they stand now, in place."""
        prm = self.params
        self._prm[0] = (prm.q_c, self.corr_samples, self.sigma_p ** 2, prm.sigma_w ** 2, self.radial_var_now(), prm.gate_nis,
                        self.k_prior_mean, self.k_prior_var, prm.max_block, _position_var(self.sigma_p), CONSISTENCY_WINDOW_S,
                        CONSISTENCY_TAU_S, MIN_RESIDUAL_SAMPLES, POSITION_RESIDUAL_LIMIT,
                        prm.arc_position_sigma ** 2)     # RUN_PARAMS' order
        return self._prm

    def eta_evidence(self) -> tuple[float, float]:
        """(k from the data alone, sigmas by which the data reject its prior mean); (the mean, 0) without
        evidence."""
        if not self.nk:
            return self.k_prior_mean, 0.0
        return eta_evidence(float(self.x[self.d]), float(self.P[self.d, self.d]), self.k_prior_mean, self.k_prior_var)

    def eta_weight(self) -> float:
        """Weight of the free-eta estimate in the report: 0 while the data do not reject the calibration,
        and 0 when the eta they ask for is implausible (more than ETA_PRIOR_LIMIT of the calibration's
        sigmas off): that is the rigid pivot failing, not eta. An object sliding in the grasp while the
        TCP runs straight reads as k -> 0 (no curvature at all)."""
        if not self.nk:
            return 0.0
        return eta_weight(float(self.x[self.d]), float(self.P[self.d, self.d]), self.k_prior_mean, self.k_prior_var,
                          self.params.eta_test_sigma)

    def report(self, x=None, P=None, consistency=None, r_last=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c, reported covariance with the eta floor, the filter's own covariance), world, of the
        state now (or of the one given: x, P, the consistency ratio and the lever arm at its last
        sample, as ekf_segments keeps them).

        The scheduled estimate (k at its prior mean: the state conditioned on it, eta's uncertainty as
        a radial floor) until the data reject that; then the free-eta estimate c = m / k is blended in
        (kernels.report_state)."""
        if x is None:
            x, P, consistency, r_last = self.x, self.P, self.consistency, self._r_last
        return report_state(x, P, self.d, max(consistency, 1.0), r_last,
                            (self.eta_rel_std / self.k_prior_mean) ** 2, self.k_prior_mean, self.k_prior_var,
                            self.params.eta_test_sigma, self._E, self.origin, self._along_var)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        p_c, cov, _ = self.report()
        return p_c, np.sqrt(np.maximum(cov.diagonal(), 0.0))
