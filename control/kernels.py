"""Compiled per-sample loops of the contact estimator: `ekf` blocks to their information (A, b), its
small linear algebra, the pipeline's rate moments, and the whole `ekf` run of a batch.

`ContactKF` (control/ekf.py) owns the model; these loops only evaluate it sample by sample. One
block is tens of samples; as numpy calls on such short arrays it cost ~60 calls (300-400 us), as
one compiled loop a few microseconds. `ekf_advance` runs a chunk (every block, the
consistency window and the position evidence) in one call, and `ekf_segments` a whole batch: the
pipeline cuts it into segments that end at each output, and the state after each segment is kept
for that output's report, which is built in Python as for every other estimator. They release the GIL and cache their machine code beside this file
(`__pycache__`, or NUMBA_CACHE_DIR). They are compiled when this module is imported, for the
signatures given (any array layout), so no call can compile mid-episode: the first import after an
install takes about 30 s on a 2-core machine, later ones about 2 s. NUMBA_DISABLE_JIT=1 runs them as
plain Python, for debugging.

The two block loops (planar_information, spatial_information) return (A, b, gated, nis,
rejected): A = sum H^T R^-1 H and b = sum H^T R^-1 y over the samples the NIS gate kept, whether
the gate was armed, each sample's NIS y^T R^-1 y (when armed) and the number it rejected. The gate
arms once H P H^T is small against R (GATE_HPH_RATIO): before that it would reject the very
samples that carry the information.
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import from_dtype, njit, types

GATE_HPH_RATIO = 0.1           # NIS gating starts once H P H^T is this small against R
# IEEE division (inf, nan) as in numpy, not Python's ZeroDivisionError; the GIL released meanwhile.
JIT = dict(nogil=True, error_model="numpy")


def jit(signature: str):
    """njit for `signature`, cached when numba finds a writable place for it (the source's
    __pycache__, NUMBA_CACHE_DIR, or the user's cache). In a read-only install with neither (a
    hardened service without NUMBA_CACHE_DIR) numba refuses to cache at all: compile each start."""
    def wrap(fn):
        try:
            return njit(signature, cache=True, **JIT)(fn)
        except RuntimeError as exc:
            if "cannot cache" not in str(exc):
                raise
            return njit(signature, cache=False, **JIT)(fn)
    return wrap


@jit("Tuple((float64[:, :], float64[:], boolean, float64[:], int64))(float64[:], float64[:], float64[:, :], "
     "float64[:, :], float64[:], float64[:], float64, float64, float64, float64, float64, float64, float64, "
     "float64, float64, float64, int64, float64, float64, float64, boolean)")
def planar_information(w_n, t_n, r0, v2, var_v, var_w, k, c0, c1, k_lin, cl0, cl1, corr, var_p, var_wn,
                       radial_var, nk, p_mm, p_kk, gate_nis, gate_allowed):
    """Planar block. w_n (n,): object rate about the plane normal at the scheduled eta; t_n (n,): the
    gripper's own rate (zeros when still); r0 (n, 2): TCP relative to the onset TCP; v2 (n, 2): TCP
    velocity; var_v, var_w (n,): extra velocity and rate variances. k, (c0, c1): the estimate;
    k_lin, (cl0, cl1): where the noise is linearised; var_p, var_wn: sigma_p^2, sigma_w^2; nk: 1 when
    eta's ratio k is a state; p_mm = P[0,0] + P[1,1], p_kk = P[2,2] (for H P H^T).

    In the plane R = a I + b u u^T + c rh rh^T with u = J r: gyro noise acts along the tangent u and
    `radial_var` along rh = r/|r|. R is diagonal in (rh, uh), so each sample is two scalar rows."""
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


@jit("Tuple((float64[:, :], float64[:], boolean, float64[:], int64))(float64[:, :], float64[:, :], float64[:, :], "
     "float64[:, :], float64[:], float64[:], float64, float64[:], float64, float64[:], float64, float64, float64, "
     "float64, int64, float64[:, :], float64, boolean)")
def spatial_information(w, w_tcp, r0, v, var_v, var_w, k, c, k_lin, c_lin, corr, var_p, var_wn, radial_var,
                        nk, P, gate_nis, gate_allowed):
    """3D block. w (n, 3): object rate at the scheduled eta; w_tcp (n, 3): the gripper's own rate
    (zeros when still); r0, v (n, 3): TCP relative to the onset TCP, and its velocity; c, c_lin (3,):
    the estimate and the linearisation point; P: the prior (3 + nk square). Per sample
    R = (sigma_w^2 + var_w) [r]x[r]x^T + corr sigma_p^2 [w]x[w]x^T + corr radial_var rh rh^T
    + corr var_v I, inverted in closed form."""
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
        r_0 = x0 - c_lin[0]
        r_1 = x1 - c_lin[1]
        r_2 = x2 - c_lin[2]
        gw = var_wn + var_w[i]
        gp = corr * var_p
        rsq = r_0 * r_0 + r_1 * r_1 + r_2 * r_2
        wsq = wl0 * wl0 + wl1 * wl1 + wl2 * wl2
        rv = (r_0, r_1, r_2)
        wv = (wl0, wl1, wl2)
        for p in range(3):
            for q in range(3):
                R[p, q] = -gw * rv[p] * rv[q] - gp * wv[p] * wv[q]
        iso = corr * var_v[i]
        if iso < iso_min:
            iso_min = iso
        for p in range(3):
            R[p, p] += gw * rsq + gp * wsq + iso
        if radial_var > 0.0:
            rnorm = max(math.sqrt(rsq), 1e-9)
            g = corr * radial_var / (rnorm * rnorm)
            for p in range(3):
                for q in range(3):
                    R[p, q] += g * rv[p] * rv[q]
        # Symmetric 3x3 inverse by cofactors.
        m00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
        m01 = R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2]
        m02 = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
        det = R[0, 0] * m00 + R[1, 0] * m01 + R[2, 0] * m02
        Ri[i, 0, 0] = m00 / det
        Ri[i, 0, 1] = m01 / det
        Ri[i, 0, 2] = m02 / det
        Ri[i, 1, 0] = Ri[i, 0, 1]
        Ri[i, 1, 1] = (R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0]) / det
        Ri[i, 1, 2] = (R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]) / det
        Ri[i, 2, 0] = Ri[i, 0, 2]
        Ri[i, 2, 1] = Ri[i, 1, 2]
        Ri[i, 2, 2] = (R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]) / det
        for p in range(3):
            for q in range(nx):
                hm[p, q] += H[i, p, q]
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


@jit("float64[:, :](float64[:, :], float64[:, :])")
def _solve_small(M, B):
    """X with M X = B for a small square M (Gaussian elimination, partial pivoting); M, B are copied."""
    n = M.shape[0]
    a = M.copy()
    x = B.copy()
    m = x.shape[1]
    for col in range(n):
        piv = col
        for r in range(col + 1, n):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if piv != col:
            for j in range(n):
                a[col, j], a[piv, j] = a[piv, j], a[col, j]
            for j in range(m):
                x[col, j], x[piv, j] = x[piv, j], x[col, j]
        inv = 1.0 / a[col, col]
        for r in range(col + 1, n):
            f = a[r, col] * inv
            if f != 0.0:
                for j in range(col, n):
                    a[r, j] -= f * a[col, j]
                for j in range(m):
                    x[r, j] -= f * x[col, j]
    for col in range(n - 1, -1, -1):
        inv = 1.0 / a[col, col]
        for j in range(m):
            s = x[col, j]
            for r in range(col + 1, n):
                s -= a[col, r] * x[r, j]
            x[col, j] = s * inv
    return x


@jit("float64[:, :](float64[:, :], float64[:, :])")
def _mm(a, b):
    """a @ b for small matrices (numba's @ needs SciPy's BLAS)."""
    out = np.zeros((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            f = a[i, k]
            for j in range(b.shape[1]):
                out[i, j] += f * b[k, j]
    return out


@jit("Tuple((float64[:], float64[:, :]))(float64[:], float64[:, :], float64[:, :], float64[:], boolean)")
def collapsed_update(x, P, A, b, commit):
    """The collapsed measurement's update from its information A, b; returns (x_new, P_new).

    A collapsed measurement H_eq (H_eq^T H_eq = A, unit noise, H_eq^T y_eq = b) has the gain
    K = P H_eq^T (H_eq P H_eq^T + I)^-1; by the push-through identity K H_eq = G A and K y_eq = G b
    with G = P (A P + I)^-1, and K K^T = G A G^T. Joseph form (I - K H) P (I - K H)^T + K K^T keeps
    P symmetric positive definite whatever the gain's rounding, with one small solve and no
    factorisation of A, whose rank may be short (the unobservable direction along a line contact).
    P_new is only formed when commit (else P is returned)."""
    n = x.shape[0]
    Mt = _mm(P, A)                    # (A P + I)^T = P A + I, as P and A are symmetric
    for i in range(n):
        Mt[i, i] += 1.0
    G = _solve_small(Mt, P).T        # P (A P + I)^-1
    x_new = x.copy()
    for i in range(n):
        for j in range(n):
            x_new[i] += G[i, j] * b[j]
    if not commit:
        return x_new, P
    GA = _mm(G, A)
    Aj = -GA
    for i in range(n):
        Aj[i, i] += 1.0
    return x_new, _mm(_mm(Aj, P), Aj.T) + _mm(GA, G.T)


@jit("Tuple((float64[:], float64[:, :], float64[:, :], float64[:, :], float64[:], boolean, float64[:], int64, "
     "float64[:, :], float64[:, :], float64))(float64[:], float64[:, :], float64[:], float64[:], float64[:, :], "
     "float64[:, :], float64[:, :], float64[:, :], float64[:, :], float64[:, :], float64[:], "
     "float64[:], float64[:, :], float64[:], float64[:], "
     "float64, float64, float64, float64, float64, float64, float64, float64, boolean, boolean)")
def block_update(x, P, x_lin, dt, w, p, v, w_v, w_tcp_v, p_v, var_v, var_w, E, nrm, origin, q_c, corr, var_p,
                 var_wn, radial_var, gate_nis, k_min, k_held, gate, commit):
    """One `ekf` block (ContactKF._block): from the world-frame samples to the updated state.

    x = [m] or [m, k] and P: the state before the block (k held at k_held when not a state); the contact's random walk (q_c m^2/s over the
    block's duration, the sum of dt) is added to P's m block first (P_prior). x_lin: where the noise is
    linearised. World, (n, 3): w and p, the object's rate at the scheduled eta and the TCP's
    position at each sample (for the position evidence and the lever arm); v, the TCP velocity held
    at each sample, and what it pairs with, from when it was measured: w_v, w_tcp_v, p_v, the
    object's rate, the gripper's own rate (zeros when still) and the TCP's position. var_v, var_w
    (n,). E (d x 3): the plane's basis, or the identity in 3D; nrm: the plane's normal (unused in
    3D); origin: the onset TCP.

    Returns (x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration): the posterior
    (P_prior again unless commit), the block's information (planar_information,
    spatial_information), the rate (n, 1) about the normal or (n, 3) and the TCP relative to the
    onset TCP (n, d) in the filter's coordinates, and the block's duration."""
    n = w.shape[0]
    d = E.shape[0]
    nk = x.shape[0] - d
    duration = 0.0
    for i in range(n):
        duration += dt[i]
    P_prior = P.copy()
    for i in range(d):
        P_prior[i, i] += q_c * duration
    k = max(x[d], k_min) if nk else k_held
    k_lin = max(x_lin[d], k_min) if nk else k_held
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
        p_kk = P_prior[2, 2] if nk else 0.0
        A, b, gated, nis, rejected = planar_information(
            w_n, t_n, r0_v, v2, var_v, var_w, k, x[0] / k, x[1] / k, k_lin, x_lin[0] / k_lin,
            x_lin[1] / k_lin, corr, var_p, var_wn, radial_var, nk, P_prior[0, 0] + P_prior[1, 1], p_kk,
            gate_nis, gate)
    else:
        w_d = w.copy()
        A, b, gated, nis, rejected = spatial_information(
            w_v, w_tcp_v, r0_v, v, var_v, var_w, k, x[:3] / k, k_lin, x_lin[:3] / k_lin, corr, var_p, var_wn,
            radial_var, nk, P_prior, gate_nis, gate)
    x_new, P_new = collapsed_update(x, P_prior, A, b, commit)
    return x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration


@jit("Tuple((float64[:], float64[:, :]))(float64[:, :])")
def sym_eig(S):
    """Eigenvalues (ascending) and eigenvectors (columns) of a small symmetric matrix, by cyclic Jacobi
    rotations: accurate in relative terms across the information matrices' wide range."""
    n = S.shape[0]
    a = S.copy()
    V = np.eye(n)
    for _ in range(60):
        off = 0.0
        diag = 0.0
        for p in range(n):
            diag += a[p, p] * a[p, p]
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        if off <= 1e-32 * diag or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    lam = np.empty(n)
    for p in range(n):
        lam[p] = a[p, p]
    order = np.argsort(lam)
    return lam[order], V[:, order]


ETA_BLEND_SIGMA = 1.0          # the free-eta estimate is blended in over this many more sigma of evidence
ETA_PRIOR_LIMIT = 4.0          # an eta ratio further than this many prior sigmas from 1 is a model failure
K_MIN = 0.2                    # floor of the eta ratio k when dividing by it (its prior is 1 +- 25 % at most)


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


@jit("float64[:, :](float64[:, :], float64[:, :], float64[:])")
def _lift(S, E, nnT_var):
    """E^T S E, plus nnT_var (a flattened 3 x 3) added."""
    out = _mm(_mm(E.T, S), E)
    for a in range(3):
        for b in range(3):
            out[a, b] += nnT_var[3 * a + b]
    return out


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
        s1 = _mm(_mm(J, P), J.T)
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
    return p, _lift(rep, E, nnT_var), _lift(stat, E, nnT_var)


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
                cov = _mm(_mm(proj, cov), proj)
                for i in range(3):
                    for j in range(3):
                        cov[i, j] += unobserved_var * axis[i] * axis[j]
            return axis, axes, cov, sym_eig(_mm(_mm(proj, stat), proj))[0][2]
    return axis, 0, cov, sym_eig(stat)[0][2]


@jit("Tuple((float64, float64))(float64[:, :], float64[:, :], float64[:], float64[:])")
def plane_rotation(stat, E, nrm, w_sum):
    """The planar report's rotation: (sign, top). sign is +1 when the summed rate w_sum turns about
    the plane's normal nrm, else -1; top is the larger eigenvalue of stat (world, 3 x 3) in the plane
    (E stat E^T, E: the plane's 2 x 3 basis), in closed form."""
    s = _mm(_mm(E, stat), E.T)
    half = 0.5 * (s[0, 0] - s[1, 1])
    top = 0.5 * (s[0, 0] + s[1, 1]) + math.sqrt(max(half * half + s[0, 1] * s[0, 1], 0.0))
    sign = 1.0 if w_sum[0] * nrm[0] + w_sum[1] * nrm[1] + w_sum[2] * nrm[2] >= 0.0 else -1.0
    return sign, top


@jit("Tuple((float64, int64))(float64[:, :], float64[:], float64)")
def pinv_quadratic(S, b, rcond):
    """(b^T S^+ b, rank) for a small symmetric positive semi-definite S, eigenvalues below
    rcond x the largest taken as zero."""
    lam, U = sym_eig(S)
    top = max(lam[-1], 1e-300)
    fit = 0.0
    rank = 0
    for j in range(lam.shape[0]):
        if lam[j] > rcond * top:
            ub = 0.0
            for i in range(b.shape[0]):
                ub += U[i, j] * b[i]
            fit += ub * ub / lam[j]
            rank += 1
    return fit, rank


@jit("void(float64[:, :], float64[:], float64[:], float64[:], float64[:, :], float64[:])")
def window_add(A_w, b_w, x0, x, A, b):
    """A_w += A; b_w += b + A (x - x0), in place: one block's data about the window's start state x0."""
    n = x.shape[0]
    for i in range(n):
        s = b[i]
        for j in range(n):
            A_w[i, j] += A[i, j]
            s += A[i, j] * (x[j] - x0[j])
        b_w[i] += s


@jit("Tuple((float64, int64))(float64[:, :], float64[:], float64[:, :])")
def window_nis(A, b, P0):
    """(NIS, rank) of a window's collapsed measurement (information A, b) against its prior P0:
    y_eq^T (H_eq P0 H_eq^T + I)^-1 y_eq = b^T A^+ b - b^T (P0^-1 + A)^-1 b (Woodbury)."""
    fit, rank = pinv_quadratic(A, b, 1e-12)
    if rank == 0:
        return 0.0, 0
    n = b.shape[0]
    Mt = _mm(P0, A)
    for i in range(n):
        Mt[i, i] += 1.0
    G = _solve_small(Mt, P0)         # (P0 A + I)^-1 P0 = (P0^-1 + A)^-1
    q = 0.0
    for i in range(n):
        for j in range(n):
            q += b[i] * G[i, j] * b[j]
    return fit - q, rank


@jit("Tuple((int64, float64))(float64[:], float64[:], float64[:], float64[:], float64[:, :], float64[:, :], "
     "float64, float64[:, :], boolean[:], float64[:, :], float64[:, :], float64[:], float64[:])")
def position_sums(theta, g, g_tcp, dt, w, w_tcp, inv_k, r, fresh, s_x, s_xx, s_xy, s_y):
    """PositionEvidence's running sums over a chunk, in place; returns (samples taken, sum of y^T y).

    w (n, 1) planar or (n, 3): the object's rate at the scheduled eta; w_tcp (same shape): the
    gripper's own rate (zeros when still); r (n, d): the TCP relative to the onset TCP. Integrated
    sample by sample: theta (1,) planar angle or (3,) rotation vector, Theta = int (w - w_tcp +
    w_tcp inv_k) dt (the m column: the gripper's rotation enters as w_tcp x m / k, linearised at
    the estimate's 1/k = inv_k); g (d,), G = int (w - w_tcp) x r dt (the k column); g_tcp (d,),
    int w_tcp x r dt (known). At each `fresh` sample the regressor X = [-[Theta]x, G] (d x (d+1);
    planar -theta J) and y = r - g_tcp enter the sums."""
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


@jit("Tuple((float64[:, :], float64[:]))(float64[:, :], float64[:, :], float64[:], float64[:], int64, float64, "
     "float64[:, :], float64[:])")
def position_increment(s_x, s_xx, s_xy, s_y, n, var, lam, xi):
    """PositionEvidence.increment: the marginal information on (m, k), the intercept q eliminated
    (Lambda = (S_xx - S_x^T S_x / n) / var, xi = (S_xy - S_x^T S_y / n) / var), returned as its
    growth since lam, xi, which are updated in place. The growth is symmetrised."""
    new, e, _ = _centred_sums(s_x, s_xx, s_xy, s_y, 0.0, n)
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


@jit("float64(float64[:, :], float64[:, :], float64[:], float64[:], float64, int64, float64, float64, int64)")
def position_residual(s_x, s_xx, s_xy, s_y, s_yy, n, var, k, min_samples):
    """PositionEvidence.residual_ratio: the (q, m) regression's residual at the held eta ratio k
    (y' = y - k G), over its expectation var * dof; 1 below min_samples or without dof.

    With the intercept eliminated (_centred_sums: L, e, c) and y' = y - k G (G: the last regressor),
    the m block is L[:d, :d], its right-hand side e[:d] - k L[:d, d], and y'^T y' is
    c - 2 k e[d] + k^2 L[d, d]."""
    d = s_x.shape[0]
    if n < min_samples:
        return 1.0
    lam, e, c = _centred_sums(s_x, s_xx, s_xy, s_y, s_yy, n)
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


# --- The `ekf` run (ContactKF.update): every block of a chunk, the consistency window and the
# position evidence, in one compiled call. Its state and parameters are named records: numpy
# structured arrays of one element (numba reads and writes their fields by name) and named tuples
# of C-contiguous arrays.
STATUS = np.dtype([
    ("steps", np.int64),           # IMU samples taken this episode
    ("rejected", np.int64),        # samples the NIS gate rejected
    ("nis", np.float64),           # the last gated sample's NIS
    ("consistency", np.float64),   # the smoothed window NIS over its expectation
    ("win_blocks", np.int64),      # the open consistency window: its blocks,
    ("win_t", np.float64),         # its duration (s),
    ("win_samples", np.int64),     # its samples seen by an armed gate,
    ("win_gated", np.int64),       # and the NIS values kept in the gated-NIS buffer
], align=True)
EVIDENCE_STATUS = np.dtype([
    ("n", np.int64),               # position samples in the sums
    ("s_yy", np.float64),          # their sum of y^T y
    ("broken", np.bool_),          # the rigid-body residual failed this episode
    ("arc", np.bool_),             # the sums began while the arm followed an arc (their noise is arc_ev_var)
], align=True)
RUN_PARAMS = np.dtype([(name, np.float64) for name in (
    "q_c",                         # m^2/s, the contact's random walk
    "corr",                        # IMU samples per proprioception sample
    "var_p",                       # m^2, TCP position noise
    "var_wn",                      # (rad/s)^2, per-sample object-rate noise
    "radial_var",                  # (m/s)^2, the arc follower's distrust along the lever arm
    "gate_nis",                    # the NIS gate (0: off)
    "k_mean",                      # eta ratio's prior mean (where k is held when not a state)
    "k_prior_var",                 # and its prior variance (0 when held)
    "max_block",                   # samples per collapsed update
    "ev_var",                      # m^2, the position evidence's noise (floored)
    "window_s",                    # s, the consistency window
    "tau_s",                       # s, the consistency ratio's smoothing
    "ev_min_samples",              # positions before the residual test can speak
    "ev_limit",                    # residual over expectation above which positions are no evidence
    "arc_ev_var",                  # m^2, the positions' noise while following an arc (0: not evidence then)
)], align=True)
Window = namedtuple("Window", "x0 P0 A b")       # the consistency window: start state, its prior, information
Evidence = namedtuple("Evidence", "status theta g g_tcp s_x s_xx s_xy s_y lam xi")   # PositionEvidence's state
Samples = namedtuple("Samples", "dt w w_tcp p v w_v w_tcp_v p_v var_v var_w fresh")   # a chunk (ContactKF.update)
Frame = namedtuple("Frame", "E nrm origin")      # the filter's coordinates: basis (d x 3), normal, onset TCP

_V, _M = types.float64[::1], types.float64[:, ::1]
STATUS_T = from_dtype(STATUS)[::1]
PARAMS_T = from_dtype(RUN_PARAMS)[::1]
WINDOW_T = types.NamedTuple((_V, _M, _M, _V), Window)
EVIDENCE_T = types.NamedTuple((from_dtype(EVIDENCE_STATUS)[::1], _V, _V, _V, _M, _M, _V, _V, _M, _V), Evidence)
SAMPLES_T = types.NamedTuple((_V, _M, _M, _M, _M, _M, _M, _M, _V, _V, types.boolean[::1]), Samples)
FRAME_T = types.NamedTuple((_M, _V, _V), Frame)


def record(dtype: np.dtype, **values) -> np.ndarray:
    """A one-element structured array of `dtype` (fields zero unless given): a named record the
    compiled run updates in place; read a field as rec[0]["name"]."""
    out = np.zeros(1, dtype)
    for name, value in values.items():
        out[0][name] = value
    return out


def contiguous(named):
    """The named tuple with each array C-contiguous (the compiled run's signatures ask for it; no copy
    when it already is)."""
    return type(named)(*(np.ascontiguousarray(a) for a in named))


@jit(types.float64[::1](types.float64[:], types.float64[:, :], STATUS_T, WINDOW_T, types.float64[::1],
                        types.float64[:, :], types.float64[:], types.float64, types.float64[:], types.int64,
                        types.int64, PARAMS_T))
def window_account(x, P_prior, status, win, gbuf, A, b, duration, nis, rejected, d, prm):
    """One committed block into the consistency window (ContactKF's divergence statistic, see
    docs/estimation.md); x is the state before the block, P_prior its prior, nis the block's
    per-sample NIS (empty when the gate was not armed). Returns the buffer of the window's gated NIS,
    grown when full.

    The window's data are one collapsed measurement of the state at its start (window_add); its NIS
    against the prior there, over its rank, smoothed over prm.tau_s, is the consistency ratio. A
    window whose samples the gate mostly rejected reads at least their median NIS over d."""
    st = status[0]
    pr = prm[0]
    ng = st.win_gated
    if rejected:
        m = nis.shape[0]
        if ng + m > gbuf.shape[0]:
            grown = np.empty(max(2 * gbuf.shape[0], ng + m))
            grown[:ng] = gbuf[:ng]
            gbuf = grown
        gbuf[ng:ng + m] = nis
        ng += m
    st.win_gated = ng
    st.win_samples += nis.shape[0]
    if st.win_blocks == 0:
        win.x0[:] = x
        win.P0[:, :] = P_prior
        win.A[:, :] = A
        win.b[:] = b
    else:
        window_add(win.A, win.b, win.x0, x, A, b)
    st.win_blocks += 1
    st.win_t += duration
    t_w = st.win_t
    if t_w < pr.window_s:
        return gbuf
    n_samples = st.win_samples
    st.win_blocks = 0
    st.win_t = 0.0
    st.win_samples = 0
    st.win_gated = 0
    ratio = 0.0
    w_nis, rank = window_nis(win.A, win.b, win.P0)
    if rank:
        # the excess over the expectation referred to the nominal length: batching cannot change it
        ratio = 1.0 + (max(w_nis, 0.0) / rank - 1.0) * (pr.window_s / t_w)
    if ng:
        over = 0
        for i in range(ng):
            if gbuf[i] > pr.gate_nis:
                over += 1
        if 2 * over > n_samples:
            ratio = max(ratio, np.median(gbuf[:ng]) / d)
    if not rank and ratio <= 0.0:
        return gbuf
    alpha = 1.0 - math.exp(-t_w / pr.tau_s)
    st.consistency += alpha * (ratio - st.consistency)
    return gbuf


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
    taken, s_yy = position_sums(ev.theta, ev.g, ev.g_tcp, dt, w_d, t_d, 1.0 / k, r0, fresh, ev.s_x, ev.s_xx, ev.s_xy,
                                ev.s_y)
    st.n += taken
    st.s_yy += s_yy
    n_ev = st.n
    if taken == 0 or n_ev < pr.ev_min_samples:
        return      # the sums grow; they count once the residual can check them
    var = max(pr.ev_var, pr.arc_ev_var) if st.arc else pr.ev_var
    d_lam, d_xi = position_increment(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, n_ev, var, ev.lam, ev.xi)
    if position_residual(ev.s_x, ev.s_xx, ev.s_xy, ev.s_y, st.s_yy, n_ev, var, k,
                         int(pr.ev_min_samples)) > pr.ev_limit:
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


@jit(types.float64[::1](_V, _M, STATUS_T, _V, WINDOW_T, types.float64[::1], EVIDENCE_T, types.boolean, SAMPLES_T,
                        types.int64, types.int64, types.boolean, FRAME_T, PARAMS_T))
def ekf_advance(x, P, status, r_last, win, gbuf, ev, ev_on, smp, i0, i1, use_fresh, frame, prm):
    """`ekf` over the samples i0:i1 of a chunk, all state updated in place; returns the gated-NIS buffer.

    State: x, P (the filter), status (STATUS), r_last (the lever arm at the last sample), the
    consistency window (win, and gbuf: its gated NIS) and, with ev_on, the position evidence (ev).
    The samples `smp` (n,): dt, w and w_tcp (world: the object's rate at the scheduled eta, the
    gripper's own rate, zeros when still), p, v (TCP), what v pairs with from when it was measured
    (w_v, w_tcp_v, p_v: block_update), var_v, var_w, and fresh (a new proprioception sample) when
    use_fresh; without it the position evidence restarts every block. frame: the filter's coordinates. prm: RUN_PARAMS.

    The chunk is one run of blocks of at most prm.max_block samples; the very first block of an
    episode is linearised about its own answer by two uncommitted passes."""
    st = status[0]
    pr = prm[0]
    d = frame.E.shape[0]
    nk = x.shape[0] - d
    mb = int(pr.max_block)
    corr = max(pr.corr, 1.0)
    for b0 in range(i0, i1, mb):
        b1 = min(b0 + mb, i1)
        steps = st.steps
        gate = pr.gate_nis > 0 and steps > 0
        # at onset the noise model is linearised about a guess: two uncommitted passes on the first
        # block (from the same prior) linearise it about the data's own answer
        passes = 3 if steps == 0 else 1
        x_lin = x
        for i in range(passes):
            out = block_update(x, P, x_lin, smp.dt[b0:b1], smp.w[b0:b1], smp.p[b0:b1], smp.v[b0:b1],
                               smp.w_v[b0:b1], smp.w_tcp_v[b0:b1], smp.p_v[b0:b1], smp.var_v[b0:b1],
                               smp.var_w[b0:b1], frame.E, frame.nrm, frame.origin,
                               pr.q_c, corr, pr.var_p, pr.var_wn, pr.radial_var, pr.gate_nis, K_MIN, pr.k_mean, gate,
                               i == passes - 1)
            x_lin = out[0]
        x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration = out
        st.rejected += rejected
        if nis.shape[0]:
            st.nis = nis[-1]
        if steps > 0:
            gbuf = window_account(x, P_prior, status, win, gbuf, A, b, duration, nis, rejected, d, prm)
        x[:] = x_new
        P[:, :] = P_new
        st.steps += b1 - b0
        k = max(x[d], K_MIN) if nk else pr.k_mean
        for a in range(d):
            r_last[a] = r0[b1 - b0 - 1, a] - x[a] / k
        if not ev_on or (use_fresh and ev.status[0].broken):
            continue
        arc = pr.radial_var > 0
        if not use_fresh or (arc and pr.arc_ev_var <= 0.0):
            # no position measurements, or following an arc with positions no evidence: restart the reference
            position_reset(ev)
            continue
        if ev.status[0].arc != arc:
            # into or out of arc following: the grasp's compliance moves the TCP along the lever arm
            # by up to the admittance's lag, so the positions then have noise of their own (arc_ev_var)
            # and a reference of their own
            position_reset(ev)
            ev.status[0].arc = arc
        t_d = np.empty(w_d.shape)
        for i in range(b1 - b0):
            if d == 2:
                t_d[i, 0] = (smp.w_tcp[b0 + i, 0] * frame.nrm[0] + smp.w_tcp[b0 + i, 1] * frame.nrm[1]
                             + smp.w_tcp[b0 + i, 2] * frame.nrm[2])
            else:
                for a in range(3):
                    t_d[i, a] = smp.w_tcp[b0 + i, a]
        position_account(x, P, ev, smp.dt[b0:b1], w_d, t_d, r0, smp.fresh[b0:b1], d, prm)
    return gbuf


@jit(types.float64[::1](_V, _M, STATUS_T, _V, WINDOW_T, types.float64[::1], EVIDENCE_T, types.boolean, SAMPLES_T,
                        types.boolean, FRAME_T, PARAMS_T, types.float64, types.int64[::1], _M,
                        types.float64[:, :, ::1], _M, _M))
def ekf_segments(x, P, status, r_last, win, gbuf, ev, ev_on, smp, use_fresh, frame, prm, slip_radial_var, ends,
                 out_x, out_P, out_r, out_s):
    """ekf_advance over the chunk's segments 0:ends[0], ends[0]:ends[1], ... (one call where the
    pipeline reports between segments), keeping the state after each of the first len(out_x): x,
    P, r_last, and (steps, nis, consistency) in out_s. Returns the gated-NIS buffer.

    As between calls one segment at a time (ContactKF.radial_var_now): once the position evidence
    has broken, the segments after take the velocity along the lever arm with at least
    slip_radial_var."""
    i0 = 0
    for j in range(ends.shape[0]):
        if ev_on and ev.status[0].broken and prm[0].radial_var < slip_radial_var:
            prm[0].radial_var = slip_radial_var
        gbuf = ekf_advance(x, P, status, r_last, win, gbuf, ev, ev_on, smp, i0, ends[j], use_fresh, frame, prm)
        i0 = ends[j]
        if j < out_x.shape[0]:
            out_x[j] = x
            out_P[j] = P
            out_r[j] = r_last
            out_s[j, 0] = status[0].steps
            out_s[j, 1] = status[0].nis
            out_s[j, 2] = status[0].consistency
    return gbuf
