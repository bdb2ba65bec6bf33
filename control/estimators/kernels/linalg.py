"""Small dense linear algebra for the compiled estimator loops (numba's own `@` and solvers need SciPy's
BLAS and LAPACK): solves, products, a symmetric eigendecomposition, the collapsed measurement's update."""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.estimators.kernels import jit


@jit("float64[:, :](float64[:, :], float64[:, :])")
def solve_small(M, B):
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
def matmul(a, b):
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
    Mt = matmul(P, A)                    # (A P + I)^T = P A + I, as P and A are symmetric
    for i in range(n):
        Mt[i, i] += 1.0
    G = solve_small(Mt, P).T        # P (A P + I)^-1
    x_new = x.copy()
    for i in range(n):
        for j in range(n):
            x_new[i] += G[i, j] * b[j]
    if not commit:
        return x_new, P
    GA = matmul(G, A)
    Aj = -GA
    for i in range(n):
        Aj[i, i] += 1.0
    return x_new, matmul(matmul(Aj, P), Aj.T) + matmul(GA, G.T)


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
    Mt = matmul(P0, A)
    for i in range(n):
        Mt[i, i] += 1.0
    G = solve_small(Mt, P0)         # (P0 A + I)^-1 P0 = (P0^-1 + A)^-1
    q = 0.0
    for i in range(n):
        for j in range(n):
            q += b[i] * G[i, j] * b[j]
    return fit - q, rank


@jit("float64[:, :](float64[:, :], float64[:, :], float64[:])")
def lift(S, E, nnT_var):
    """E^T S E, plus nnT_var (a flattened 3 x 3) added."""
    out = matmul(matmul(E.T, S), E)
    for a in range(3):
        for b in range(3):
            out[a, b] += nnT_var[3 * a + b]
    return out
