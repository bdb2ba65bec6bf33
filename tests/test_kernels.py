"""The compiled estimator loops (control/kernels.py) against plain numpy evaluations of the same model."""
import numpy as np
import pytest

from control import kernels as K

REL_TOL = 1e-9


def skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def information(samples, nx):
    """sum H^T R^-1 H and sum H^T R^-1 y over (H, y, R) per sample."""
    A, b = np.zeros((nx, nx)), np.zeros(nx)
    for H, y, R in samples:
        Ri = np.linalg.inv(R)
        A += H.T @ Ri @ H
        b += H.T @ Ri @ y
    return A, b


def spatial_samples(w, w_tcp, r0, v, var_v, var_w, k, c, k_lin, c_lin, corr, var_p, var_wn, radial_var, nk):
    """(H, y, R) of ContactKF's 3D model, sample by sample in numpy."""
    for i in range(len(w)):
        rel = w[i] - w_tcp[i]
        w_true, a3, w_lin = w_tcp[i] + k * rel, rel + w_tcp[i] / k, w_tcp[i] + k_lin * rel
        H = np.zeros((3, 3 + nk))
        H[:, :3] = -skew(a3)
        if nk:
            H[:, 3] = np.cross(rel, r0[i]) + np.cross(w_tcp[i], c / k)
        y = v[i] - np.cross(w_true, r0[i] - c)
        r = r0[i] - c_lin
        R = (var_wn + var_w[i]) * skew(r) @ skew(r).T + corr * var_p * skew(w_lin) @ skew(w_lin).T \
            + corr * var_v[i] * np.eye(3)
        if radial_var > 0:
            rh = r / np.linalg.norm(r)
            R += corr * radial_var * np.outer(rh, rh)
        yield H, y, R


def planar_samples(w_n, t_n, r0, v2, var_v, var_w, k, c, k_lin, c_lin, corr, var_p, var_wn, radial_var, nk):
    """The same in a plane: w x r = w_n J r, gyro noise along the tangent, radial_var along the lever arm."""
    J = np.array([[0.0, -1.0], [1.0, 0.0]])
    for i in range(len(w_n)):
        rel = w_n[i] - t_n[i]
        w_true, a_n, w_lin = t_n[i] + k * rel, rel + t_n[i] / k, t_n[i] + k_lin * rel
        H = np.zeros((2, 2 + nk))
        H[:, :2] = -a_n * J
        if nk:
            H[:, 2] = rel * J @ r0[i] + t_n[i] * J @ c / k
        y = v2[i] - w_true * J @ (r0[i] - c)
        r = r0[i] - c_lin
        u = J @ r
        R = corr * (var_v[i] + var_p * w_lin ** 2) * np.eye(2) + (var_wn + var_w[i]) * np.outer(u, u) \
            + corr * radial_var * np.outer(r, r) / (r @ r)
        yield H, y, R


def assert_same_information(A, b, A_ref, b_ref):
    np.testing.assert_allclose(A, A_ref, rtol=REL_TOL, atol=REL_TOL * np.abs(A_ref).max())
    np.testing.assert_allclose(b, b_ref, rtol=REL_TOL, atol=REL_TOL * np.abs(b_ref).max())


def block(rng, n=33):
    w = np.array([0.1, -0.3, 0.2]) + rng.normal(0, 0.01, (n, 3))
    r0 = np.array([0.1, 0.02, -0.05]) + rng.normal(0, 1e-3, (n, 3))
    v = rng.normal(0, 0.02, (n, 3))
    return w, r0, v, rng.uniform(1e-7, 1e-6, n), rng.uniform(0, 1e-5, n)


@pytest.mark.parametrize("turning", [False, True])
@pytest.mark.parametrize("radial_var", [0.0, 2.5e-5])
@pytest.mark.parametrize("nk", [0, 1])
def test_spatial_information_matches_numpy(turning, radial_var, nk):
    rng = np.random.default_rng(1)
    w, r0, v, var_v, var_w = block(rng)
    w_tcp = np.tile([0.0, -0.1, 0.05], (len(w), 1)) if turning else np.zeros_like(w)
    args = (1.1, np.array([0.01, 0.0, -0.02]), 1.05, np.array([0.012, 0.001, -0.018]), 3.0, 2.5e-9, 1e-4,
            radial_var, nk)
    A, b, gated, nis, rejected = K.spatial_information(w, w_tcp, r0, v, var_v, var_w, *args, np.eye(3 + nk),
                                                       16.3, False)
    A_ref, b_ref = information(spatial_samples(w, w_tcp, r0, v, var_v, var_w, *args), 3 + nk)
    assert_same_information(A, b, A_ref, b_ref)
    assert not gated and len(nis) == 0 and rejected == 0


@pytest.mark.parametrize("turning", [False, True])
@pytest.mark.parametrize("radial_var", [0.0, 2.5e-5])
@pytest.mark.parametrize("nk", [0, 1])
def test_planar_information_matches_numpy(turning, radial_var, nk):
    rng = np.random.default_rng(2)
    w, r0, v, var_v, var_w = block(rng)
    w_n, r2, v2 = w[:, 1].copy(), r0[:, :2].copy(), v[:, :2].copy()
    t_n = np.full(len(w_n), -0.1) if turning else np.zeros(len(w_n))
    c, c_lin = np.array([0.01, -0.02]), np.array([0.012, -0.018])
    A, b, gated, nis, rejected = K.planar_information(
        w_n, t_n, r2, v2, var_v, var_w, 1.1, c[0], c[1], 1.05, c_lin[0], c_lin[1], 3.0, 2.5e-9, 1e-4, radial_var,
        nk, 1.0, 1.0, 16.3, False)
    A_ref, b_ref = information(planar_samples(w_n, t_n, r2, v2, var_v, var_w, 1.1, c, 1.05, c_lin, 3.0, 2.5e-9,
                                              1e-4, radial_var, nk), 2 + nk)
    assert_same_information(A, b, A_ref, b_ref)


def test_gate_rejects_an_outlier_once_armed():
    rng = np.random.default_rng(3)
    w, r0, v, var_v, var_w = block(rng)
    w_tcp = np.zeros_like(w)
    c = np.zeros(3)
    v = np.cross(w, r0)                    # consistent with contact at the origin, k = 1
    v[5] += [0.5, 0.0, 0.0]                # one glitch
    args = (w, w_tcp, r0, v, var_v, var_w, 1.0, c, 1.0, c, 1.0, 2.5e-9, 1e-4, 0.0, 0)
    _, _, gated, nis, rejected = K.spatial_information(*args, np.eye(3) * 1e-12, 16.3, True)
    assert gated and rejected == 1 and nis[5] > 16.3 and np.all(np.delete(nis, 5) < 16.3)
    _, _, gated, _, rejected = K.spatial_information(*args, np.eye(3) * 0.25, 16.3, True)
    assert not gated and rejected == 0      # the prior is still wide: H P H^T is large against R


def test_collapsed_update_is_the_kalman_update_of_an_equivalent_measurement():
    """Joseph form through the push-through identity equals the textbook update with H_eq from A's
    square root, also when A is rank-deficient (a line contact)."""
    rng = np.random.default_rng(4)
    for rank in (1, 2, 4):
        B = rng.normal(size=(rank, 4)) * 30.0
        A, b = B.T @ B, B.T @ rng.normal(size=rank)
        L = rng.normal(size=(4, 4))
        P, x = L @ L.T * 1e-3 + 1e-4 * np.eye(4), rng.normal(size=4)
        x_new, P_new = K.collapsed_update(x, P, A, b, True)
        lam, U = np.linalg.eigh(A)
        good = lam > 1e-12 * lam[-1]
        H = np.sqrt(lam[good])[:, None] * U[:, good].T
        y = (U[:, good].T @ b) / np.sqrt(lam[good])
        S = H @ P @ H.T + np.eye(len(y))
        Kg = P @ H.T @ np.linalg.inv(S)
        np.testing.assert_allclose(x_new, x + Kg @ y, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(P_new, (np.eye(4) - Kg @ H) @ P, rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(P_new, P_new.T, atol=1e-15)
        nis, r = K.window_nis(A, b, P)
        assert r == rank and nis == pytest.approx(y @ np.linalg.solve(S, y), rel=1e-7)


def test_sym_eig_matches_numpy_across_wide_ranges():
    rng = np.random.default_rng(5)
    for n in (2, 3, 4):
        for _ in range(50):
            B = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 6, size=(n, 1))
            S = B @ B.T
            lam, V = K.sym_eig(S)
            np.testing.assert_allclose(lam, np.linalg.eigvalsh(S), rtol=1e-9, atol=1e-12 * np.abs(S).max())
            np.testing.assert_allclose(V @ np.diag(lam) @ V.T, S, rtol=1e-9, atol=1e-10 * np.abs(S).max())


def test_kernels_divide_by_zero_as_numpy_does():
    """IEEE division, not Python's ZeroDivisionError: a degenerate sample cannot raise in the estimator thread."""
    n = 2
    zeros = np.zeros((n, 3))
    A, b, *_ = K.spatial_information(zeros, zeros, zeros, zeros, np.zeros(n), np.zeros(n), 1.0, np.zeros(3), 1.0,
                                     np.zeros(3), 1.0, 0.0, 0.0, 0.0, 1, np.eye(4), 16.3, False)
    assert A.shape == (4, 4)


def test_jit_compiles_where_numba_cannot_cache():
    """A read-only install without NUMBA_CACHE_DIR: numba refuses cache=True; the loops still compile."""
    ns = {}
    exec("def twice(x):\n    return 2.0 * x\n", ns)        # no source file: nowhere to cache
    with pytest.raises(RuntimeError, match="cannot cache"):
        K.njit("float64(float64)", cache=True)(ns["twice"])
    assert K.jit("float64(float64)")(ns["twice"])(1.5) == 3.0
