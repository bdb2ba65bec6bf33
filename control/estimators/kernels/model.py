"""`ekf`'s measurement model, compiled: a block of samples to its information (A, b), and one block's update.

ContactKF (control/estimators/ekf.py) owns the model and control/estimators/reference.py states it
in numpy; these loops only evaluate it sample by sample. One block is tens of samples; as numpy
calls on such short arrays it cost about 60 calls (300-400 us), as one compiled loop a few
microseconds.

The two block loops (planar_information, spatial_information) return (A, b, gated, nis, rejected):
A = sum H^T R^-1 H and b = sum H^T R^-1 y over the samples the NIS gate kept, whether the gate was
armed, each sample's NIS y^T R^-1 y (when armed) and the number it rejected. The gate arms once
H P H^T is small against R (GATE_HPH_RATIO): before that it would reject the very samples that
carry the information.
"""
from __future__ import annotations

import math

import numpy as np
from numba import types

from tecdard.control.estimators.kernels import jit
from tecdard.control.estimators.kernels.constants import GATE_HPH_RATIO, K_MIN
from tecdard.control.estimators.kernels.linalg import collapsed_update
from tecdard.control.estimators.kernels.nbtypes import FRAME_T, PARAMS_T, SAMPLES_T


@jit(types.Tuple((types.float64[:, :], types.float64[:], types.boolean, types.float64[:], types.int64))(
    types.float64[:], types.float64[:], types.float64[:, :], types.float64[:, :], types.float64[:], types.float64[:],
    types.float64[:], types.float64[:], types.float64[:, :], PARAMS_T, types.boolean))
def planar_information(w_n, t_n, r0, v2, var_v, var_w, x, x_lin, P, prm, gate_allowed):
    """Planar block. w_n (n,): object rate about the plane normal at the scheduled eta; t_n (n,): the
    gripper's own rate (zeros when still); r0 (n, 2): TCP relative to the onset TCP; v2 (n, 2): TCP
    velocity; var_v, var_w (n,): extra velocity and rate variances. x = [m] or [m, k]: the estimate
    (k held at prm's k_mean when it is not a state), x_lin: where the noise is linearised, P: the
    prior (for H P H^T); the noise from prm (RUN_PARAMS).

    In the plane R = a I + b u u^T + c rh rh^T with u = J r: gyro noise acts along the tangent u and
    `radial_var` along rh = r/|r|. R is diagonal in (rh, uh), so each sample is two scalar rows."""
    pr = prm[0]
    nk = x.shape[0] - 2
    k = max(x[2], K_MIN) if nk else pr.k_mean
    k_lin = max(x_lin[2], K_MIN) if nk else pr.k_mean
    c0, c1 = x[0] / k, x[1] / k
    cl0, cl1 = x_lin[0] / k_lin, x_lin[1] / k_lin
    corr, var_p, var_wn, radial_var, gate_nis = max(pr.corr, 1.0), pr.var_p, pr.var_wn, pr.radial_var, pr.gate_nis
    p_mm = P[0, 0] + P[1, 1]
    p_kk = P[2, 2] if nk else 0.0
    n = w_n.shape[0]
    nx = 2 + nk
    yr = np.empty(n)
    yu = np.empty(n)
    inv_r = np.empty(n)
    inv_u = np.empty(n)
    cr = np.empty((n, 3))
    cu = np.empty((n, 3))
    a_min = np.inf
    s_a2 = 0.0
    s_hk2 = 0.0
    for i in range(n):
        tn = t_n[i]
        rel = w_n[i] - tn
        w_true = tn + k * rel
        a_n = rel + tn / k
        w_lin = tn + k_lin * rel
        r0x = r0[i, 0]
        r0y = r0[i, 1]
        # y = v - w_true J (r0 - c); H = [-a_n J, dh/dk]
        yx = v2[i, 0] + w_true * (r0y - c1)
        yy = v2[i, 1] - w_true * (r0x - c0)
        rx = r0x - cl0
        ry = r0y - cl1
        rr = rx * rx + ry * ry + 1e-18
        rn = math.sqrt(rr)
        ex = rx / rn
        ey = ry / rn
        a = corr * (var_v[i] + var_p * w_lin * w_lin)
        if a < a_min:
            a_min = a
        inv_r[i] = 1.0 / (a + corr * radial_var)          # along the lever arm
        inv_u[i] = 1.0 / (a + (var_wn + var_w[i]) * rr)   # along the tangent
        yr[i] = ex * yx + ey * yy
        yu[i] = ex * yy - ey * yx
        # H's columns on (rh, uh): -a_n J e1 = (0, -a_n), -a_n J e2 = (a_n, 0), dh/dk.
        cr[i, 0] = -a_n * ey
        cr[i, 1] = a_n * ex
        cu[i, 0] = -a_n * ex
        cu[i, 1] = -a_n * ey
        s_a2 += a_n * a_n
        if nk:
            # dh/dk = rel J r0 + t_n J c / k
            hkx = -(rel * r0y + tn * c1 / k)
            hky = rel * r0x + tn * c0 / k
            cr[i, 2] = ex * hkx + ey * hky
            cu[i, 2] = ex * hky - ey * hkx
            s_hk2 += hkx * hkx + hky * hky
    hph = s_a2 / n * p_mm
    if nk:
        hph += s_hk2 / n * p_kk
    gated = gate_allowed and hph < GATE_HPH_RATIO * 2.0 * a_min
    nis = np.empty(n if gated else 0)
    A = np.zeros((nx, nx))
    b = np.zeros(nx)
    rejected = 0
    for i in range(n):
        if gated:
            e = yr[i] * yr[i] * inv_r[i] + yu[i] * yu[i] * inv_u[i]
            nis[i] = e
            if not e <= gate_nis:
                rejected += 1
                continue
        for p in range(nx):
            wr = cr[i, p] * inv_r[i]
            wu = cu[i, p] * inv_u[i]
            b[p] += wr * yr[i] + wu * yu[i]
            for q in range(nx):
                A[p, q] += wr * cr[i, q] + wu * cu[i, q]
    return A, b, gated, nis, rejected


@jit()
def _noise_3x3(R, r_0, r_1, r_2, wl0, wl1, wl2, gw, gp, iso, g_radial):
    """R = gw [r]x[r]x^T + gp [w]x[w]x^T + iso I + g_radial rh rh^T, in place (r: the lever arm where
    the noise is linearised, w: the rate there)."""
    rsq = r_0 * r_0 + r_1 * r_1 + r_2 * r_2
    wsq = wl0 * wl0 + wl1 * wl1 + wl2 * wl2
    rv = (r_0, r_1, r_2)
    wv = (wl0, wl1, wl2)
    for p in range(3):
        for q in range(3):
            R[p, q] = -gw * rv[p] * rv[q] - gp * wv[p] * wv[q]
    for p in range(3):
        R[p, p] += gw * rsq + gp * wsq + iso
    if g_radial > 0.0:
        rnorm = max(math.sqrt(rsq), 1e-9)
        g = g_radial / (rnorm * rnorm)
        for p in range(3):
            for q in range(3):
                R[p, q] += g * rv[p] * rv[q]


@jit()
def _invert_sym3(R, out):
    """out = R^-1 for a symmetric 3 x 3 R, by cofactors."""
    m00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
    m01 = R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2]
    m02 = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
    det = R[0, 0] * m00 + R[1, 0] * m01 + R[2, 0] * m02
    out[0, 0] = m00 / det
    out[0, 1] = m01 / det
    out[0, 2] = m02 / det
    out[1, 0] = out[0, 1]
    out[1, 1] = (R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0]) / det
    out[1, 2] = (R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]) / det
    out[2, 0] = out[0, 2]
    out[2, 1] = out[1, 2]
    out[2, 2] = (R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]) / det


@jit()
def _gated_information(H, y, Ri, hm, iso_min, P, nx, gate_nis, gate_allowed):
    """The 3D block's (A, b, gated, nis, rejected) from its rows (_spatial_rows)."""
    n = y.shape[0]
    # Gate once trace(Hm P Hm^T) is small against the velocity noise. (H removes the unobservable
    # direction along w, so a line contact's large along-edge variance does not count.)
    hph = 0.0
    for p in range(3):
        for q in range(nx):
            s = 0.0
            for r in range(nx):
                s += P[q, r] * hm[p, r]
            hph += hm[p, q] * s
    hph /= n * n
    gated = gate_allowed and hph < GATE_HPH_RATIO * 3.0 * iso_min
    nis = np.empty(n if gated else 0)
    A = np.zeros((nx, nx))
    b = np.zeros(nx)
    hr = np.empty((4, 3))
    rejected = 0
    for i in range(n):
        if gated:
            e = 0.0
            for p in range(3):
                for q in range(3):
                    e += y[i, p] * Ri[i, p, q] * y[i, q]
            nis[i] = e
            if not e <= gate_nis:
                rejected += 1
                continue
        for p in range(nx):             # H^T R^-1
            for q in range(3):
                hr[p, q] = H[i, 0, p] * Ri[i, 0, q] + H[i, 1, p] * Ri[i, 1, q] + H[i, 2, p] * Ri[i, 2, q]
        for p in range(nx):
            b[p] += hr[p, 0] * y[i, 0] + hr[p, 1] * y[i, 1] + hr[p, 2] * y[i, 2]
            for q in range(nx):
                A[p, q] += hr[p, 0] * H[i, 0, q] + hr[p, 1] * H[i, 1, q] + hr[p, 2] * H[i, 2, q]
    return A, b, gated, nis, rejected


@jit()
def _spatial_rows(w, w_tcp, r0, v, var_v, var_w, lin, nk, prm):
    """Each sample's Jacobian H (n, 3, 4), innovation y (n, 3) and inverse noise Ri (n, 3, 3), with the
    sum of the H (for the gate) and the smallest isotropic noise term. lin: k, c, k_lin, c_lin."""
    pr = prm[0]
    corr, var_p, var_wn, radial_var = max(pr.corr, 1.0), pr.var_p, pr.var_wn, pr.radial_var
    k = lin[0]
    c = lin[1:4]
    k_lin = lin[4]
    c_lin = lin[5:8]
    n = w.shape[0]
    nx = 3 + nk
    H = np.zeros((n, 3, 4))
    y = np.empty((n, 3))
    Ri = np.empty((n, 3, 3))
    hm = np.zeros((3, 4))
    iso_min = np.inf
    R = np.empty((3, 3))
    ck = c / k
    for i in range(n):
        rel0 = w[i, 0] - w_tcp[i, 0]
        rel1 = w[i, 1] - w_tcp[i, 1]
        rel2 = w[i, 2] - w_tcp[i, 2]
        wt0 = w_tcp[i, 0] + k * rel0
        wt1 = w_tcp[i, 1] + k * rel1
        wt2 = w_tcp[i, 2] + k * rel2
        a0 = rel0 + w_tcp[i, 0] / k
        a1 = rel1 + w_tcp[i, 1] / k
        a2 = rel2 + w_tcp[i, 2] / k
        wl0 = w_tcp[i, 0] + k_lin * rel0
        wl1 = w_tcp[i, 1] + k_lin * rel1
        wl2 = w_tcp[i, 2] + k_lin * rel2
        x0 = r0[i, 0]
        x1 = r0[i, 1]
        x2 = r0[i, 2]
        # -[a]x: H m = m x a
        H[i, 0, 1] = a2
        H[i, 0, 2] = -a1
        H[i, 1, 0] = -a2
        H[i, 1, 2] = a0
        H[i, 2, 0] = a1
        H[i, 2, 1] = -a0
        if nk:
            # dh/dk = rel x r0 + w_tcp x c / k
            H[i, 0, 3] = rel1 * x2 - rel2 * x1 + w_tcp[i, 1] * ck[2] - w_tcp[i, 2] * ck[1]
            H[i, 1, 3] = rel2 * x0 - rel0 * x2 + w_tcp[i, 2] * ck[0] - w_tcp[i, 0] * ck[2]
            H[i, 2, 3] = rel0 * x1 - rel1 * x0 + w_tcp[i, 0] * ck[1] - w_tcp[i, 1] * ck[0]
        # y = v - w_true x (r0 - c)
        d0 = x0 - c[0]
        d1 = x1 - c[1]
        d2 = x2 - c[2]
        y[i, 0] = v[i, 0] - (wt1 * d2 - wt2 * d1)
        y[i, 1] = v[i, 1] - (wt2 * d0 - wt0 * d2)
        y[i, 2] = v[i, 2] - (wt0 * d1 - wt1 * d0)
        iso = corr * var_v[i]
        if iso < iso_min:
            iso_min = iso
        _noise_3x3(R, x0 - c_lin[0], x1 - c_lin[1], x2 - c_lin[2], wl0, wl1, wl2, var_wn + var_w[i], corr * var_p,
                   iso, corr * radial_var)
        _invert_sym3(R, Ri[i])
        for p in range(3):
            for q in range(nx):
                hm[p, q] += H[i, p, q]
    return H, y, Ri, hm, iso_min


@jit(types.Tuple((types.float64[:, :], types.float64[:], types.boolean, types.float64[:], types.int64))(
    types.float64[:, :], types.float64[:, :], types.float64[:, :], types.float64[:, :], types.float64[:],
    types.float64[:], types.float64[:], types.float64[:], types.float64[:, :], PARAMS_T, types.boolean))
def spatial_information(w, w_tcp, r0, v, var_v, var_w, x, x_lin, P, prm, gate_allowed):
    """3D block. w (n, 3): object rate at the scheduled eta; w_tcp (n, 3): the gripper's own rate
    (zeros when still); r0, v (n, 3): TCP relative to the onset TCP, and its velocity; x = [m] or
    [m, k]: the estimate (k held at prm's k_mean when it is not a state), x_lin: where the noise is
    linearised; P: the prior (3 + nk square). Per sample
    R = (sigma_w^2 + var_w) [r]x[r]x^T + corr sigma_p^2 [w]x[w]x^T + corr radial_var rh rh^T
    + corr var_v I, inverted in closed form."""
    pr = prm[0]
    nk = x.shape[0] - 3
    k = max(x[3], K_MIN) if nk else pr.k_mean
    k_lin = max(x_lin[3], K_MIN) if nk else pr.k_mean
    lin = np.empty(8)                    # k, c (3), k_lin, c_lin (3)
    lin[0] = k
    lin[1:4] = x[:3] / k
    lin[4] = k_lin
    lin[5:8] = x_lin[:3] / k_lin
    H, y, Ri, hm, iso_min = _spatial_rows(w, w_tcp, r0, v, var_v, var_w, lin, nk, prm)
    return _gated_information(H, y, Ri, hm, iso_min, P, 3 + nk, pr.gate_nis, gate_allowed)


@jit(types.Tuple((types.float64[:], types.float64[:, :], types.float64[:, :], types.float64[:, :], types.float64[:],
                  types.boolean, types.float64[:], types.int64, types.float64[:, :], types.float64[:, :],
                  types.float64))(types.float64[:], types.float64[:, :], types.float64[:], SAMPLES_T, types.int64,
                                  types.int64, FRAME_T, PARAMS_T, types.boolean, types.boolean))
def block_update(x, P, x_lin, smp, b0, b1, frame, prm, gate, commit):
    """One `ekf` block, the samples b0:b1 of the chunk `smp` (records.Samples): from the world-frame
    samples to the updated state.

    x = [m] or [m, k] and P: the state before the block (k held at prm's k_mean when not a state); the
    contact's random walk (q_c m^2/s over the block's duration, the sum of dt) is added to P's m block
    first (P_prior). x_lin: where the noise is linearised. From the chunk: w and p, the object's rate
    at the scheduled eta and the TCP's position at each sample (for the position evidence and the
    lever arm); v, the TCP velocity held at each sample, and what it pairs with, from when it was
    measured: w_v, w_tcp_v, p_v, the object's rate, the gripper's own rate (zeros when still) and the
    TCP's position; var_v, var_w. frame (records.Frame): the plane's basis E (d x 3, the identity in
    3D), its normal, the onset TCP. gate: the NIS gate may arm.

    Returns (x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration): the posterior
    (P_prior again unless commit), the block's information (planar_information,
    spatial_information), the rate (n, 1) about the normal or (n, 3) and the TCP relative to the
    onset TCP (n, d) in the filter's coordinates, and the block's duration."""
    dt, w, p, v = smp.dt[b0:b1], smp.w[b0:b1], smp.p[b0:b1], smp.v[b0:b1]
    w_v, w_tcp_v, p_v = smp.w_v[b0:b1], smp.w_tcp_v[b0:b1], smp.p_v[b0:b1]
    var_v, var_w = smp.var_v[b0:b1], smp.var_w[b0:b1]
    E, nrm, origin = frame.E, frame.nrm, frame.origin
    q_c = prm[0].q_c
    n = w.shape[0]
    d = E.shape[0]
    duration = 0.0
    for i in range(n):
        duration += dt[i]
    P_prior = P.copy()
    for i in range(d):
        P_prior[i, i] += q_c * duration
    r0 = np.empty((n, d))
    r0_v = np.empty((n, d))
    for i in range(n):
        for a in range(d):
            s = 0.0
            s_v = 0.0
            for j in range(3):
                s += (p[i, j] - origin[j]) * E[a, j]
                s_v += (p_v[i, j] - origin[j]) * E[a, j]
            r0[i, a] = s
            r0_v[i, a] = s_v
    if d == 2:
        w_d = np.empty((n, 1))
        w_n = np.empty(n)
        t_n = np.empty(n)
        v2 = np.empty((n, 2))
        for i in range(n):
            w_d[i, 0] = w[i, 0] * nrm[0] + w[i, 1] * nrm[1] + w[i, 2] * nrm[2]
            w_n[i] = w_v[i, 0] * nrm[0] + w_v[i, 1] * nrm[1] + w_v[i, 2] * nrm[2]
            t_n[i] = w_tcp_v[i, 0] * nrm[0] + w_tcp_v[i, 1] * nrm[1] + w_tcp_v[i, 2] * nrm[2]
            for a in range(2):
                v2[i, a] = v[i, 0] * E[a, 0] + v[i, 1] * E[a, 1] + v[i, 2] * E[a, 2]
        A, b, gated, nis, rejected = planar_information(w_n, t_n, r0_v, v2, var_v, var_w, x, x_lin, P_prior, prm,
                                                        gate)
    else:
        w_d = w.copy()
        A, b, gated, nis, rejected = spatial_information(w_v, w_tcp_v, r0_v, v, var_v, var_w, x, x_lin, P_prior,
                                                         prm, gate)
    x_new, P_new = collapsed_update(x, P_prior, A, b, commit)
    return x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration
