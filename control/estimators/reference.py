"""`ekf-reference`: `ekf` written out in numpy, in filterpy's shape: the readable statement of ContactKF's
model, and the reference its compiled run (control/estimators/kernels/) is tested against.

ContactKF (control/estimators/ekf.py) documents the model; this module states it. The state is x = [m] or
[m, k]: k = eta_true / eta_used, m = k c, c the contact relative to the onset TCP (plane
coordinates when planar). Each IMU sample i measures the TCP velocity

    z_i = v_i,   h_i(x) = w_true x (r0_i - c),   w_true = w_tcp + k (w - w_tcp)

(r0: the TCP relative to the onset TCP). With the gripper still h is linear in x; a turning
gripper's term w_tcp x c / k is linearised at the estimate. Its noise R_i holds the velocity noise
(plus staleness), the gyro noise through [r]x, the position noise through [w]x, and along the lever
arm the arc follower's distrust; every term but the gyro's is inflated by the samples that share
one proprioception sample (`corr`: their errors are one error).

A block of up to `max_block` samples is one step: `predict` (the contact's random walk) then
`update` with the block's samples stacked, the samples the NIS gate rejects left out. The compiled
run applies the same information, collapsed to one equivalent measurement, so the two agree to
rounding. What it adds to the filter:
- the consistency ratio: a window's (about 10 ms of blocks) NIS against the prior at its start,
  over its rank, smoothed (the daemon's divergence stop reads it);
- the positions as evidence (control.estimators.positions.PositionEvidence: the running sums in compiled code,
  tested against numpy there), applied in information form;
- the report: the scheduled estimate, eta's floor and the free-eta blend (`report`).
"""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.estimators.base import CONSISTENCY_TAU_S, UNOBSERVED_STD_M, ContactEstimator, EstimatorSpec
from tecdard.control.estimators.ekf import CONSISTENCY_WINDOW_S, ContactKfParams, ContactKfSettings
from tecdard.control.estimators.kernels.api import ETA_PRIOR_LIMIT, GATE_HPH_RATIO, K_MIN, eta_weight
from tecdard.control.estimators.positions import MIN_RESIDUAL_SAMPLES, POSITION_RESIDUAL_LIMIT, PositionEvidence
from tecdard.control.geometry import Plane, skew
from tecdard.control.measurements import Samples

J = np.array([[0.0, -1.0], [1.0, 0.0]])      # w x r in a plane: w_n J r
RANK_RCOND = 1e-12                           # eigenvalues of a window's information below this x the largest: zero


def information_update(x: np.ndarray, P: np.ndarray, A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, P) after a linear measurement given by its information A = H^T R^-1 H, b = H^T R^-1 y.
    G = P (A P + I)^-1 is the gain on b; Joseph form for the covariance, as in `ContactFilter.update`."""
    n = len(x)
    G = np.linalg.solve(P @ A + np.eye(n), P).T
    IGA = np.eye(n) - G @ A
    return x + G @ b, IGA @ P @ IGA.T + G @ A @ G.T


def report(x: np.ndarray, P: np.ndarray, d: int, scale: float, r_last: np.ndarray, eta_var: float, k_mean: float,
           wgt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ContactKF's report in the filter's coordinates: (c, reported covariance, statistical covariance).

    The scheduled estimate (m / k_mean, the state conditioned on k = k_mean, eta's relative variance
    eta_var as a floor along the lever arm r_last), blended with the free-eta estimate m / k by wgt
    (kernels.eta_weight) with the spread between the two; covariances scaled by `scale`."""
    m = x[:d]
    if len(x) > d:
        pmk, pkk = P[:d, d], P[d, d]
        c0, s0 = m + pmk * (k_mean - x[d]) / pkk, P[:d, :d] - np.outer(pmk, pmk) / pkk
    else:
        c0, s0 = m.copy(), P[:d, :d].copy()
    c0, s0 = c0 / k_mean, s0 * scale / k_mean ** 2
    rep0 = s0 + eta_var * scale * np.outer(r_last, r_last)
    if wgt <= 0.0:
        return c0, rep0, s0
    k = max(x[d], K_MIN)
    Jc = np.hstack([np.eye(d) / k, (-m / k ** 2)[:, None]])
    c1, s1 = m / k, Jc @ P @ Jc.T * scale
    spread = wgt * (1.0 - wgt) * np.outer(c1 - c0, c1 - c0)
    return c0 + wgt * (c1 - c0), (1 - wgt) * rep0 + wgt * s1 + spread, (1 - wgt) * s0 + wgt * s1 + spread


class ContactFilter:
    """The filter proper, as filterpy's KalmanFilter keeps it: x, P, the prior (x_prior, P_prior)
    and the posterior (x_post, P_post), the last step's innovation y, its covariance S and its NIS."""

    def __init__(self, x: np.ndarray, P: np.ndarray, q_c: float, d: int):
        self.x, self.P = x.astype(float).copy(), P.astype(float).copy()
        self.q_c, self.d = q_c, d
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self.x_post, self.P_post = self.x.copy(), self.P.copy()
        self.y = np.zeros(0)
        self.S = np.zeros((0, 0))
        self.nis = 0.0

    def predict(self, duration_s: float) -> None:
        """The contact is fixed but may creep: Q = q_c * duration on m, none on k."""
        Q = np.zeros_like(self.P)
        Q[:self.d, :self.d] = self.q_c * duration_s * np.eye(self.d)
        self.P = self.P + Q
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, y: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """A stacked measurement: innovation y = z - h(x_prior), its Jacobian H and noise R."""
        P = self.P
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T           # P H^T S^-1 (S symmetric)
        self.y, self.S = y, S
        self.nis = float(y @ np.linalg.solve(S, y))
        self.x = self.x + K @ y
        # Joseph form: symmetric and positive definite whatever the gain's rounding.
        IKH = np.eye(len(self.x)) - K @ H
        self.P = IKH @ P @ IKH.T + K @ R @ K.T
        self.x_post, self.P_post = self.x.copy(), self.P.copy()


class ReferenceKF(ContactKfSettings, ContactEstimator):
    """`ekf-reference`: ContactKF's model and schedule in numpy; the same estimates, slower."""

    method = "ekf-reference"

    def __init__(self, params: ContactKfParams | None = None, plane: Plane | None = None):
        self.params = params or ContactKfParams()
        self.plane = plane
        self.d = 2 if plane is not None else 3
        self.nk = 1 if self.params.estimate_eta else 0
        self.E = plane.E if plane is not None else np.eye(3)
        self.sigma_p = self.params.sigma_p
        self.corr_samples = 1.0
        self.radial_var = 0.0
        self._radial_var = 0.0                  # the distrust along the lever arm for the current chunk
        self.eta_prior_mean, self.eta_rel_std = 1.0, self.params.eta_rel_std
        self.k_prior_mean, self.k_prior_var = 1.0, 0.0
        self.origin = np.zeros(3)
        self.kf = ContactFilter(np.zeros(self.d + self.nk), np.eye(self.d + self.nk), self.params.q_c, self.d)
        self.positions = PositionEvidence(self.d, self.sigma_p, self.params.arc_position_sigma) \
            if self.params.use_positions else None
        self.r_last = np.zeros(self.d)
        self.steps = self.rejected = 0
        self.nis = 0.0
        self.consistency = 1.0
        self.window = None

    @property
    def x(self) -> np.ndarray:
        return self.kf.x

    @property
    def P(self) -> np.ndarray:
        return self.kf.P

    def k(self, x: np.ndarray | None = None) -> float:
        """The eta ratio at x (the estimate by default), floored; its prior mean when not a state."""
        x = self.kf.x if x is None else x
        return max(float(x[self.d]), K_MIN) if self.nk else self.k_prior_mean

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        x0, P0 = self._episode_prior(p_g)
        self.kf = ContactFilter(x0, P0, self.params.q_c, self.d)
        self.steps = self.rejected = 0
        self.nis = 0.0
        self.consistency = 1.0
        self.window = None

    # --- the measurement model
    def _samples(self, w, w_tcp, p, v):
        """The block in the filter's coordinates: (rate, gripper rate, r0, v); rates are scalars about
        the normal when planar."""
        r0 = (p - self.origin) @ self.E.T
        if self.plane is None:
            return w, w_tcp, r0, v
        n = self.plane.n
        return w @ n, w_tcp @ n, r0, v @ self.E.T

    def model(self, x: np.ndarray, x_lin: np.ndarray, w, w_tcp, r0, v, var_v, var_w):
        """Per sample (n of them): innovation y (n, d), Jacobian H (n, d, nx) and noise R (n, d, d) at
        the state x, the noise linearised at x_lin."""
        d, nk, prm = self.d, self.nk, self.params
        k, k_lin = self.k(x), self.k(x_lin)
        radial_var = self._radial_var          # as of the chunk's start, as the compiled run reads it
        c, c_lin = x[:d] / k, x_lin[:d] / k_lin
        corr = max(self.corr_samples, 1.0)
        n = len(r0)
        y, H, R = np.empty((n, d)), np.zeros((n, d, d + nk)), np.empty((n, d, d))
        for i in range(n):
            rel = w[i] - w_tcp[i]
            w_true = w_tcp[i] + k * rel
            a = rel + w_tcp[i] / k                # dh/dm = -[a]x: m enters as k rel x m / k + w_tcp x m / k
            w_lin = w_tcp[i] + k_lin * rel
            r = r0[i] - c_lin                     # the lever arm where the noise is linearised
            if d == 2:
                y[i] = v[i] - w_true * J @ (r0[i] - c)
                H[i, :, :2] = -a * J
                if nk:
                    H[i, :, 2] = rel * J @ r0[i] + w_tcp[i] * J @ c / k
                u = J @ r
                R[i] = (corr * (var_v[i] + self.sigma_p ** 2 * w_lin ** 2) * np.eye(2)
                        + (prm.sigma_w ** 2 + var_w[i]) * np.outer(u, u))
                rh = r / math.sqrt(r @ r + 1e-18)
            else:
                y[i] = v[i] - np.cross(w_true, r0[i] - c)
                H[i, :, :3] = -skew(a)
                if nk:
                    H[i, :, 3] = np.cross(rel, r0[i]) + np.cross(w_tcp[i], c / k)
                R[i] = ((prm.sigma_w ** 2 + var_w[i]) * skew(r) @ skew(r).T
                        + corr * self.sigma_p ** 2 * skew(w_lin) @ skew(w_lin).T + corr * var_v[i] * np.eye(3))
                rh = r / max(float(np.linalg.norm(r)), 1e-9)
            R[i] += corr * radial_var * np.outer(rh, rh)
        return y, H, R

    def gate_armed(self, H: np.ndarray, R_floor: float, P: np.ndarray) -> bool:
        """The NIS gate arms once the state's uncertainty, seen through the block's H, is small against
        the measurement noise (GATE_HPH_RATIO): before that it would reject the samples that carry the
        information. R_floor: the smallest isotropic noise term of the block."""
        d = self.d
        if d == 2:
            hph = np.mean(H[:, 0, 1] ** 2) * (P[0, 0] + P[1, 1])
            if self.nk:
                hph += np.mean(np.sum(H[:, :, 2] ** 2, axis=1)) * P[2, 2]
        else:
            Hm = H.mean(axis=0)
            hph = float(np.trace(Hm @ P @ Hm.T))
        return hph < GATE_HPH_RATIO * d * R_floor

    def _block(self, x_lin, dt, w, w_tcp, p, v, w_v, w_tcp_v, p_v, var_v, var_w, commit: bool):
        """One block: predict, gate, update. The model pairs each held velocity v with the rates and
        the position from when it was measured (w_v, w_tcp_v, p_v); the position evidence takes the
        rates and positions at each sample. Returns what the window and the positions need."""
        kf, prm = self.kf, self.params
        d = self.d
        x0, P0 = kf.x.copy(), kf.P.copy()
        duration = float(np.sum(dt))
        kf.predict(duration)
        wd, wt, r0, vd = self._samples(w_v, w_tcp_v, p_v, v)
        y, H, R = self.model(kf.x, x_lin, wd, wt, r0, vd, var_v, var_w)
        corr = max(self.corr_samples, 1.0)
        if d == 2:
            k_lin = self.k(x_lin)
            w_lin = wt + k_lin * (wd - wt)
            R_floor = float(np.min(corr * (var_v + self.sigma_p ** 2 * w_lin ** 2)))
        else:
            R_floor = float(np.min(corr * var_v))
        gated = prm.gate_nis > 0 and self.steps > 0 and self.gate_armed(H, R_floor, kf.P)
        nis = np.array([yi @ np.linalg.solve(Ri, yi) for yi, Ri in zip(y, R)]) if gated else np.zeros(0)
        keep = (nis <= prm.gate_nis) if gated else np.ones(len(y), bool)
        rejected = int(np.count_nonzero(~keep))
        Hs = H[keep].reshape(-1, d + self.nk)
        ys = y[keep].reshape(-1)
        Rs = np.zeros((len(ys), len(ys)))
        for j, Ri in enumerate(R[keep]):
            Rs[j * d:(j + 1) * d, j * d:(j + 1) * d] = Ri
        P_prior = kf.P.copy()
        Ri_all = np.linalg.inv(Rs) if len(ys) else Rs
        A, b = Hs.T @ Ri_all @ Hs, Hs.T @ Ri_all @ ys
        if len(ys):
            kf.update(ys, Hs, Rs)
        if not commit:
            x_new = kf.x.copy()
            kf.x, kf.P = x0, P0
            return x_new, None
        w_now, w_tcp_now, r0_now, _ = self._samples(w, w_tcp, p, v)
        return kf.x.copy(), dict(x=x0, P_prior=P_prior, A=A, b=b, nis=nis, rejected=rejected, duration=duration,
                                 w=w_now, w_tcp=w_tcp_now, r0=r0_now)

    # --- the run over a chunk (ContactEstimator)
    def update(self, samples: Samples) -> None:
        """A run of samples, as ContactKF takes them (ContactKfSettings._inputs)."""
        run, use_fresh = self._inputs(samples)
        n = len(run.dt)
        self._radial_var = self.radial_var_now()
        mb = self.params.max_block
        for b0 in range(0, n, mb):
            sl = slice(b0, b0 + mb)
            args = (run.dt[sl], run.w[sl], run.w_tcp[sl], run.p[sl], run.v[sl], run.w_v[sl], run.w_tcp_v[sl],
                    run.p_v[sl], run.var_v[sl], run.var_w[sl])
            # at onset the noise is linearised about a guess: two passes on the first block (from the
            # same prior, not kept) linearise it about the data's own answer
            x_lin = self.kf.x
            for _ in range(2 if self.steps == 0 else 0):
                x_lin, _ = self._block(x_lin, *args, commit=False)
            _, blk = self._block(x_lin, *args, commit=True)
            self.rejected += blk["rejected"]
            if len(blk["nis"]):
                self.nis = float(blk["nis"][-1])
            if self.steps > 0:
                self._window(blk)
            self.steps += len(args[0])
            self.r_last = blk["r0"][-1] - self.kf.x[:self.d] / self.k()
            self._positions(blk, args[0], run.fresh[sl] if use_fresh else None)

    def _window(self, blk: dict) -> None:
        """The consistency ratio: the blocks of about CONSISTENCY_WINDOW_S are one measurement of the
        state at the window's start; its NIS against the prior there, over its rank, smoothed."""
        if self.window is None:
            self.window = dict(x0=blk["x"], P0=blk["P_prior"], A=blk["A"].copy(), b=blk["b"].copy(), t=0.0,
                               gated=[], n=0)
        else:
            win = self.window
            win["b"] = win["b"] + blk["b"] + blk["A"] @ (blk["x"] - win["x0"])   # the block's y at x0
            win["A"] = win["A"] + blk["A"]
        win = self.window
        win["t"] += blk["duration"]
        win["n"] += len(blk["nis"])
        if blk["rejected"]:
            win["gated"].append(blk["nis"])
        if win["t"] < CONSISTENCY_WINDOW_S:
            return
        self.window = None
        lam, U = np.linalg.eigh(win["A"])
        live = lam > RANK_RCOND * max(lam[-1], 1e-300)
        rank = int(np.count_nonzero(live))
        ratio = 0.0
        if rank:
            ub = U[:, live].T @ win["b"]
            fit = float(np.sum(ub ** 2 / lam[live]))                  # b^T A^+ b
            n = len(win["b"])
            inv = np.linalg.solve(win["P0"] @ win["A"] + np.eye(n), win["P0"])   # (P0^-1 + A)^-1
            nis = fit - float(win["b"] @ inv @ win["b"])              # y^T (H P0 H^T + R)^-1 y, collapsed
            ratio = 1.0 + (max(nis, 0.0) / rank - 1.0) * (CONSISTENCY_WINDOW_S / win["t"])
        if win["gated"]:
            every = np.concatenate(win["gated"])
            if 2 * np.count_nonzero(every > self.params.gate_nis) > win["n"]:
                ratio = max(ratio, float(np.median(every)) / self.d)
        if rank or ratio > 0.0:
            self.consistency += (1.0 - math.exp(-win["t"] / CONSISTENCY_TAU_S)) * (ratio - self.consistency)

    def _positions(self, blk: dict, dt: np.ndarray, fresh: np.ndarray | None) -> None:
        """The positions' new information about (m, k), once enough are in and they fit a rigid pivot."""
        ev = self.positions
        if ev is None or (fresh is not None and ev.broken):
            return
        arc = self._radial_var > 0
        if fresh is None or (arc and ev.arc_var <= 0.0):
            ev.reset()                  # no positions, or following an arc with positions no evidence
            return
        if ev.ev.status[0]["arc"] != arc:
            ev.reset()                  # into or out of arc following: a reference and a noise of their own
            ev.ev.status[0]["arc"] = arc
        if self.nk and self.k_prior_var > 0:
            if abs(float(self.kf.x[self.d]) - self.k_prior_mean) > ETA_PRIOR_LIMIT * math.sqrt(self.k_prior_var):
                ev.set_broken()         # an implausible eta: the rigid pivot fails, not eta
                return
        if not ev.add(dt, blk["w"], blk["r0"], fresh, blk["w_tcp"], self.k()) or ev.n < MIN_RESIDUAL_SAMPLES:
            return
        d_lam, d_xi = ev.increment()
        if ev.residual_ratio(self.k()) > POSITION_RESIDUAL_LIMIT:
            ev.set_broken()             # the TCP moves relative to the object
            return
        n = self.d + self.nk                 # with k held, its column is part of the measurement
        b = d_xi - d_lam @ np.append(self.kf.x[:self.d], self.k())
        self.kf.x, self.kf.P = information_update(self.kf.x, self.kf.P, d_lam[:n, :n], b[:n])

    def report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c, reported covariance with eta's floor, the filter's own covariance), world."""
        d, x, P = self.d, self.kf.x, self.kf.P
        eta_var = (self.eta_rel_std / self.k_prior_mean) ** 2
        wgt = eta_weight(float(x[d]), float(P[d, d]), self.k_prior_mean, self.k_prior_var,
                         self.params.eta_test_sigma) if self.nk else 0.0
        c, rep, stat = report(x, P, d, max(self.consistency, 1.0), self.r_last, eta_var, self.k_prior_mean, wgt)
        along = UNOBSERVED_STD_M ** 2 * self.plane.nnT if self.plane is not None else np.zeros((3, 3))
        E = self.E
        return self.origin + c @ E, E.T @ rep @ E + along, E.T @ stat @ E + along


ESTIMATORS = (EstimatorSpec("ekf-reference",
                            "`ekf` in numpy, block by block: the readable model the compiled run is tested against",
                            lambda options, plane: ReferenceKF(options, plane), "ekf", ContactKfParams),)
