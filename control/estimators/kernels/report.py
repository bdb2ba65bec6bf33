"""What every output reports, compiled: `ekf`'s report of its state (eta's floor and the free-eta blend),
and the pipeline's rate moments, rotation axis and plane sign, which every estimator's output carries."""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.estimators.kernels import jit
from tecdard.control.estimators.kernels.constants import ETA_BLEND_SIGMA, ETA_PRIOR_LIMIT, K_MIN
from tecdard.control.estimators.kernels.linalg import lift, matmul, sym_eig



@jit("Tuple((float64, float64))(float64, float64, float64, float64)")
def eta_evidence(x_k, pkk, k_mean, k_prior_var):
    """(k from the data alone, sigmas by which the data reject the prior's k_mean) for the eta ratio's
    estimate x_k, its variance pkk and its prior N(k_mean, k_prior_var); (k_mean, 0) without evidence."""
    if k_prior_var <= 0.0 or pkk <= 0.0:
        return k_mean, 0.0
    info = 1.0 / pkk - 1.0 / k_prior_var     # posterior information less the prior's
    if info <= 1e-12 / k_prior_var:
        return k_mean, 0.0
    k_data = (x_k / pkk - k_mean / k_prior_var) / info
    return k_data, abs(k_data - k_mean) * math.sqrt(info)


@jit("float64(float64, float64, float64, float64, float64)")
def eta_weight(x_k, pkk, k_mean, k_prior_var, test_sigma):
    """Weight of the free-eta estimate in the report (ContactKF.eta_weight)."""
    k_data, z = eta_evidence(x_k, pkk, k_mean, k_prior_var)
    if abs(k_data - k_mean) > ETA_PRIOR_LIMIT * math.sqrt(k_prior_var):
        return 0.0
    return min(max((z - test_sigma) / ETA_BLEND_SIGMA, 0.0), 1.0)


@jit("Tuple((float64[:], float64[:, :], float64[:, :]))(float64[:], float64[:, :], int64, float64, float64[:], "
     "float64, float64, float64, float64, float64[:, :], float64[:], float64[:])")
def report_state(x, P, d, scale, r_last, eta_var, k_mean, k_prior_var, test_sigma, E, origin, nnT_var):
    """ContactKF's report, lifted to the world: (p_c, reported covariance, statistical covariance).

    The state is x = [m] or [m, k] (d = len(m)), P its covariance, scaled by `scale` (the
    consistency ratio, at least 1). The scheduled estimate is m / k_mean with the state conditioned
    on k = k_mean (eta's prior; k is held there when it is not a state), with eta's relative
    variance `eta_var` as a radial floor along the lever arm `r_last`; once the data reject k_mean
    (eta_weight) the free-eta estimate m / k (covariance through the Jacobian [I / k, -m / k^2]) is
    blended in, with the spread between the two. The filter's coordinates
    map to the world by p = origin + c E (E: d x 3, the plane's basis, or the identity) and
    S -> E^T S E + nnT_var (the variance along the plane's normal, zeros in 3D)."""
    nk = x.shape[0] - d
    pkk = P[d, d] if nk else 0.0
    c = np.empty(d)
    s0 = np.empty((d, d))
    inv = 1.0 / k_mean
    if pkk > 0.0:
        f = k_mean - x[d]
        for i in range(d):
            c[i] = (x[i] + P[i, d] * f / pkk) * inv
            for j in range(d):
                s0[i, j] = (P[i, j] - P[i, d] * (P[j, d] / pkk)) * scale * inv * inv
    else:
        for i in range(d):
            c[i] = x[i] * inv
            for j in range(d):
                s0[i, j] = P[i, j] * scale * inv * inv
    rep = np.empty((d, d))
    for i in range(d):
        for j in range(d):
            rep[i, j] = s0[i, j] + r_last[i] * (eta_var * scale * r_last[j])
    wgt = eta_weight(x[d], pkk, k_mean, k_prior_var, test_sigma) if nk else 0.0
    stat = s0
    if wgt > 0.0:
        k = max(x[d], K_MIN)
        J = np.zeros((d, d + 1))
        dc = np.empty(d)
        for i in range(d):
            J[i, i] = 1.0 / k
            J[i, d] = -x[i] / (k * k)
            dc[i] = x[i] / k - c[i]
        s1 = matmul(matmul(J, P), J.T)
        for i in range(d):
            c[i] += wgt * dc[i]
            for j in range(d):
                shared = wgt * s1[i, j] * scale + wgt * (1.0 - wgt) * dc[i] * dc[j]
                rep[i, j] = (1.0 - wgt) * rep[i, j] + shared
                stat[i, j] = (1.0 - wgt) * stat[i, j] + shared
    p = origin.copy()
    for a in range(3):
        for i in range(d):
            p[a] += c[i] * E[i, a]
    return p, lift(rep, E, nnT_var), lift(stat, E, nnT_var)


@jit("void(float64[:, :], float64[:, :, :], float64[:, :], float64[:, :], int64, float64[:], float64[:, :], "
     "float64[:], float64[:], float64[:, :], float64[:, :, :], float64[:, :, :])")
def report_states(xs, Ps, rs, ss, d, eta, E, origin, nnT_var, p_out, rep_out, stat_out):
    """report_state for each of a run's outputs (xs, Ps, rs: the state, covariance and lever arm of
    each; ss[:, 2] the consistency ratio, scaled as at least 1; eta: report_state's (eta_var, k_mean,
    k_prior_var, test_sigma)), into p_out (m, 3), rep_out and stat_out (m, 3, 3): one call for the
    some 200 outputs a second of recording makes."""
    for j in range(xs.shape[0]):
        p, rep, stat = report_state(xs[j], Ps[j], d, max(ss[j, 2], 1.0), rs[j], eta[0], eta[1], eta[2], eta[3], E,
                                    origin, nnT_var)
        for a in range(3):
            p_out[j, a] = p[a]
            for b in range(3):
                rep_out[j, a, b] = rep[a, b]
                stat_out[j, a, b] = stat[a, b]


@jit("Tuple((float64[:], int64, float64[:, :], float64))(float64[:, :], float64[:], int64, float64, float64[:, :], "
     "float64[:, :], float64, float64, float64)")
def rotation_axes(wwT, w_sum, n_w, var_w, cov, stat, min_rate2, second_ratio, unobserved_var):
    """The 3D report's rotation axis from the rate moments (rate_moments): (axis, axes, cov, top).

    The principal axis of the mean w w^T, less the gyro noise var_w, signed as the rotation; axes is
    0 while no rate reaches min_rate2, 2 when a second axis reaches second_ratio of the first (a
    point contact is then observable), else 1: a line contact (edge, hinge), unobservable along the
    axis, where cov is replaced by its projection on the plane of rotation plus unobserved_var along
    the axis. top is the largest eigenvalue of stat in the plane of rotation (of stat without an
    axis)."""
    axis = np.zeros(3)
    if n_w > 0:
        S = wwT / n_w
        for i in range(3):
            S[i, i] -= var_w
        lam, vecs = sym_eig(S)
        if lam[2] >= min_rate2:
            sign = 1.0 if vecs[0, 2] * w_sum[0] + vecs[1, 2] * w_sum[1] + vecs[2, 2] * w_sum[2] >= 0.0 else -1.0
            for i in range(3):
                axis[i] = sign * vecs[i, 2]
            proj = np.eye(3)
            for i in range(3):
                for j in range(3):
                    proj[i, j] -= axis[i] * axis[j]
            axes = 2 if lam[1] > second_ratio * lam[2] else 1
            if axes == 1:
                cov = matmul(matmul(proj, cov), proj)
                for i in range(3):
                    for j in range(3):
                        cov[i, j] += unobserved_var * axis[i] * axis[j]
            return axis, axes, cov, sym_eig(matmul(matmul(proj, stat), proj))[0][2]
    return axis, 0, cov, sym_eig(stat)[0][2]


@jit("Tuple((float64, float64))(float64[:, :], float64[:, :], float64[:], float64[:])")
def plane_rotation(stat, E, nrm, w_sum):
    """The planar report's rotation: (sign, top). sign is +1 when the summed rate w_sum turns about
    the plane's normal nrm, else -1; top is the larger eigenvalue of stat (world, 3 x 3) in the plane
    (E stat E^T, E: the plane's 2 x 3 basis), in closed form."""
    s = matmul(matmul(E, stat), E.T)
    half = 0.5 * (s[0, 0] - s[1, 1])
    top = 0.5 * (s[0, 0] + s[1, 1]) + math.sqrt(max(half * half + s[0, 1] * s[0, 1], 0.0))
    sign = 1.0 if w_sum[0] * nrm[0] + w_sum[1] * nrm[1] + w_sum[2] * nrm[2] >= 0.0 else -1.0
    return sign, top


@jit("float64(float64[:, :], float64[:], float64[:, :], float64[:])")
def rate_moments(w, dt, wwT, w_sum):
    """wwT += sum w w^T and w_sum += sum w over a block, in place; returns sum |w| dt (the angle turned)."""
    angle = 0.0
    for i in range(w.shape[0]):
        w0 = w[i, 0]
        w1 = w[i, 1]
        w2 = w[i, 2]
        w_sum[0] += w0
        w_sum[1] += w1
        w_sum[2] += w2
        wwT[0, 0] += w0 * w0
        wwT[0, 1] += w0 * w1
        wwT[0, 2] += w0 * w2
        wwT[1, 1] += w1 * w1
        wwT[1, 2] += w1 * w2
        wwT[2, 2] += w2 * w2
        angle += math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * dt[i]
    wwT[1, 0] = wwT[0, 1]
    wwT[2, 0] = wwT[0, 2]
    wwT[2, 1] = wwT[1, 2]
    return angle


@jit("Tuple((int64, int64))(float64[:], float64, float64, int64[:])")
def output_ends(ts, t_out, period, ends):
    """The segments of a run of samples stamped ts that end at each output time (ContactPipeline._advance):
    an output is due at the first sample at or after t_out + period, t_out is then that sample's time.
    Writes each segment's end (exclusive row index) into ends; returns (segments, outputs due): every
    segment is due but perhaps the last, which ends at len(ts)."""
    n = ts.shape[0]
    m = 0
    n_due = 0
    k0 = 0
    while k0 < n:
        due = np.searchsorted(ts, t_out + period)
        k1 = n if due >= n else max(due + 1, k0 + 1)
        ends[m] = k1
        m += 1
        if due < n:
            t_out = ts[k1 - 1]
            n_due += 1
        k0 = k1
    return m, n_due


@jit("void(float64[:, :], float64[:], int64[:], float64[:, :], float64[:], float64[:], float64[:, :, :], "
     "float64[:, :])")
def segment_moments(w, dt, ends, wwT, w_sum, angles, wwT_after, w_sum_after):
    """rate_moments over each segment in turn (ends: exclusive row indices): wwT and w_sum accumulate in
    place as segment by segment; each segment's angle, and the moments after it, are written out."""
    k0 = 0
    for j in range(ends.shape[0]):
        k1 = ends[j]
        angles[j] = rate_moments(w[k0:k1], dt[k0:k1], wwT, w_sum)
        for a in range(3):
            w_sum_after[j, a] = w_sum[a]
            for b in range(3):
                wwT_after[j, a, b] = wwT[a, b]
        k0 = k1
