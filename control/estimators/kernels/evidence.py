"""The TCP positions as evidence (control.estimators.positions.PositionEvidence), compiled: the
regression's running sums, its marginal information with the intercept eliminated, its rigid-body
residual, and one committed block's positions into the `ekf` state."""
from __future__ import annotations

import math

import numpy as np
from numba import types

from tecdard.control.estimators.kernels import jit
from tecdard.control.estimators.kernels.constants import ETA_PRIOR_LIMIT, K_MIN
from tecdard.control.estimators.kernels.linalg import collapsed_update, pinv_quadratic
from tecdard.control.estimators.kernels.nbtypes import EVIDENCE_T, PARAMS_T


@jit(types.Tuple((types.int64, types.float64))(EVIDENCE_T, types.float64[:], types.float64[:, :], types.float64[:, :],
                                              types.float64, types.float64[:, :], types.boolean[:]))
def position_sums(ev, dt, w, w_tcp, inv_k, r, fresh):
    """PositionEvidence's running sums over a chunk, in place; returns (samples taken, sum of y^T y).

    w (n, 1) planar or (n, 3): the object's rate at the scheduled eta; w_tcp (same shape): the
    gripper's own rate (zeros when still); r (n, d): the TCP relative to the onset TCP. Integrated
    sample by sample: theta (1,) planar angle or (3,) rotation vector, Theta = int (w - w_tcp +
    w_tcp inv_k) dt (the m column: the gripper's rotation enters as w_tcp x m / k, linearised at
    the estimate's 1/k = inv_k); g (d,), G = int (w - w_tcp) x r dt (the k column); g_tcp (d,),
    int w_tcp x r dt (known). At each `fresh` sample the regressor X = [-[Theta]x, G] (d x (d+1);
    planar -theta J) and y = r - g_tcp enter the sums (s_x, s_xx, s_xy, s_y)."""
    theta, g, g_tcp, s_x, s_xx, s_xy, s_y = ev.theta, ev.g, ev.g_tcp, ev.s_x, ev.s_xx, ev.s_xy, ev.s_y
    n = dt.shape[0]
    d = r.shape[1]
    taken = 0
    s_yy = 0.0
    X = np.zeros((d, d + 1))
    y = np.empty(d)
    for i in range(n):
        if d == 2:
            tdt = w_tcp[i, 0] * dt[i]
            rdt = w[i, 0] * dt[i] - tdt
            theta[0] += rdt + tdt * inv_k
            g[0] -= rdt * r[i, 1]
            g[1] += rdt * r[i, 0]
            g_tcp[0] -= tdt * r[i, 1]
            g_tcp[1] += tdt * r[i, 0]
        else:
            t0 = w_tcp[i, 0] * dt[i]
            t1 = w_tcp[i, 1] * dt[i]
            t2 = w_tcp[i, 2] * dt[i]
            w0 = w[i, 0] * dt[i] - t0
            w1 = w[i, 1] * dt[i] - t1
            w2 = w[i, 2] * dt[i] - t2
            theta[0] += w0 + t0 * inv_k
            theta[1] += w1 + t1 * inv_k
            theta[2] += w2 + t2 * inv_k
            g[0] += w1 * r[i, 2] - w2 * r[i, 1]
            g[1] += w2 * r[i, 0] - w0 * r[i, 2]
            g[2] += w0 * r[i, 1] - w1 * r[i, 0]
            g_tcp[0] += t1 * r[i, 2] - t2 * r[i, 1]
            g_tcp[1] += t2 * r[i, 0] - t0 * r[i, 2]
            g_tcp[2] += t0 * r[i, 1] - t1 * r[i, 0]
        if not fresh[i]:
            continue
        if d == 2:
            X[0, 1] = theta[0]
            X[1, 0] = -theta[0]
        else:
            X[0, 1] = theta[2]
            X[0, 2] = -theta[1]
            X[1, 0] = -theta[2]
            X[1, 2] = theta[0]
            X[2, 0] = theta[1]
            X[2, 1] = -theta[0]
        for j in range(d):
            X[j, d] = g[j]
            y[j] = r[i, j] - g_tcp[j]
        taken += 1
        for j in range(d):
            s_y[j] += y[j]
            s_yy += y[j] * y[j]
            for a in range(d + 1):
                s_x[j, a] += X[j, a]
                s_xy[a] += X[j, a] * y[j]
                for b in range(d + 1):
                    s_xx[a, b] += X[j, a] * X[j, b]
    return taken, s_yy


@jit("Tuple((float64[:, :], float64[:], float64))(float64[:, :], float64[:, :], float64[:], float64[:], float64, "
     "int64)")
def _centred_sums(s_x, s_xx, s_xy, s_y, s_yy, n):
    """PositionEvidence's running sums with the regression's intercept q eliminated:
    (S_xx - S_x^T S_x / n, S_xy - S_x^T S_y / n, S_yy - S_y^T S_y / n), n at least 1."""
    d, nx = s_x.shape[0], s_x.shape[1]
    nn = max(n, 1)
    lam = np.empty((nx, nx))
    xi = np.empty(nx)
    for a in range(nx):
        for b in range(nx):
            sxx = 0.0
            for j in range(d):
                sxx += s_x[j, a] * s_x[j, b]
            lam[a, b] = s_xx[a, b] - sxx / nn
        sxy = 0.0
        for j in range(d):
            sxy += s_x[j, a] * s_y[j]
        xi[a] = s_xy[a] - sxy / nn
    syy = 0.0
    for j in range(d):
        syy += s_y[j] * s_y[j]
    return lam, xi, s_yy - syy / nn


@jit(types.Tuple((types.float64[:, :], types.float64[:]))(EVIDENCE_T, types.int64, types.float64))
def position_increment(ev, n, var):
    """PositionEvidence.increment: the marginal information on (m, k), the intercept q eliminated
    (Lambda = (S_xx - S_x^T S_x / n) / var, xi = (S_xy - S_x^T S_y / n) / var), returned as its
    growth since ev's lam, xi, which are updated in place. The growth is symmetrised."""
    lam, xi = ev.lam, ev.xi
    new, e, _ = _centred_sums(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, 0.0, n)
    nx = new.shape[0]
    d_lam = np.empty((nx, nx))
    d_xi = np.empty(nx)
    for a in range(nx):
        d_xi[a] = e[a] / var - xi[a]
        xi[a] = e[a] / var
        for b in range(nx):
            d_lam[a, b] = 0.5 * ((new[a, b] + new[b, a]) / var - lam[a, b] - lam[b, a])
    for a in range(nx):
        for b in range(nx):
            lam[a, b] = new[a, b] / var
    return d_lam, d_xi


@jit(types.float64(EVIDENCE_T, types.float64, types.int64, types.float64, types.float64, types.int64))
def position_residual(ev, s_yy, n, var, k, min_samples):
    """PositionEvidence.residual_ratio: the (q, m) regression's residual at the held eta ratio k
    (y' = y - k G), over its expectation var * dof; 1 below min_samples or without dof.

    With the intercept eliminated (_centred_sums: L, e, c) and y' = y - k G (G: the last regressor),
    the m block is L[:d, :d], its right-hand side e[:d] - k L[:d, d], and y'^T y' is
    c - 2 k e[d] + k^2 L[d, d]."""
    d = ev.s_x.shape[0]
    if n < min_samples:
        return 1.0
    lam, e, c = _centred_sums(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, s_yy, n)
    lam_u = lam[:d, :d].copy()
    eta_u = np.empty(d)
    for a in range(d):
        eta_u[a] = e[a] - k * lam[a, d]
    fit, rank = pinv_quadratic(lam_u, eta_u, 1e-9)     # the fitted m's share of the sum of squares
    dof = d * n - d - rank
    if dof <= 0:
        return 1.0
    rss = c - 2.0 * k * e[d] + k * k * lam[d, d] - fit
    return max(rss, 0.0) / (var * dof)


@jit(types.void(EVIDENCE_T))
def position_reset(ev):
    """PositionEvidence restarts its reference: no samples, integrals and sums zero (broken is kept)."""
    ev.status[0].n = 0
    ev.status[0].s_yy = 0.0
    ev.theta[:] = 0.0
    ev.g[:] = 0.0
    ev.g_tcp[:] = 0.0
    ev.s_x[:, :] = 0.0
    ev.s_xx[:, :] = 0.0
    ev.s_xy[:] = 0.0
    ev.s_y[:] = 0.0
    ev.lam[:, :] = 0.0
    ev.xi[:] = 0.0


@jit(types.void(types.float64[:], types.float64[:, :], EVIDENCE_T, types.float64[:], types.float64[:, :],
                types.float64[:, :], types.float64[:, :], types.boolean[:], types.int64, PARAMS_T))
def position_account(x, P, ev, dt, w_d, t_d, r0, fresh, d, prm):
    """One committed block's positions (PositionEvidence) into the state x, P, in place: the running
    sums grow; once prm.ev_min_samples positions are in and the rigid-body residual (at the held eta
    ratio) stays below prm.ev_limit, their new information is one collapsed update. Above the limit,
    or once they have pulled the eta ratio's estimate beyond ETA_PRIOR_LIMIT prior sigmas, the
    evidence is broken for the episode. w_d, t_d: the object's and the gripper's rates in the
    filter's coordinates ((n, 1) about the normal, or (n, 3))."""
    st = ev.status[0]
    pr = prm[0]
    nk = x.shape[0] - d
    k = max(x[d], K_MIN) if nk else pr.k_mean
    if nk and pr.k_prior_var > 0.0:
        if abs(x[d] - pr.k_mean) > ETA_PRIOR_LIMIT * math.sqrt(pr.k_prior_var):
            # the displacements ask for an eta the calibration rules out: the rigid pivot fails
            # (a slip, or a twist too large for one eta), not eta
            st.broken = True
            return
    taken, s_yy = position_sums(ev, dt, w_d, t_d, 1.0 / k, r0, fresh)
    st.n += taken
    st.s_yy += s_yy
    n_ev = st.n
    if taken == 0 or n_ev < pr.ev_min_samples:
        return      # the sums grow; they count once the residual can check them
    var = max(pr.ev_var, pr.arc_ev_var) if st.arc else pr.ev_var
    d_lam, d_xi = position_increment(ev, n_ev, var)
    if position_residual(ev, st.s_yy, n_ev, var, k, int(pr.ev_min_samples)) > pr.ev_limit:
        st.broken = True            # the TCP moves relative to the object: displacements mislead
        return
    n = d + nk                      # with k held, its column is part of the measurement
    b = np.empty(n)
    for a in range(n):
        s = d_xi[a]
        for j in range(d):
            s -= d_lam[a, j] * x[j]
        b[a] = s - d_lam[a, d] * k
    x_new, P_new = collapsed_update(x, P, d_lam[:n, :n].copy(), b, True)
    x[:] = x_new
    P[:, :] = P_new
