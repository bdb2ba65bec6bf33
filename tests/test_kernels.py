"""The compiled estimator loops (control/estimators/kernels/) against plain numpy evaluations of the same model."""
import numpy as np
import pytest
from numba import njit

from tecdard.control.estimators import reference
from tecdard.control.estimators.kernels import evidence, jit, linalg, model, records, report

REL_TOL = 1e-9
REFERENCE_REL_TOL = 1e-7    # the compiled run against control/reference.py: a collapsed and a stacked update


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


def linearised(k, c, k_lin, c_lin, nk):
    """(x, x_lin, k_mean): the state and the linearisation point that put the model at (k, c) and
    (k_lin, c_lin). With k held (nk 0) it is the prior mean, at both."""
    if nk:
        return np.append(c * k, k), np.append(c_lin * k_lin, k_lin), 1.0
    return c * k, c_lin * k, k


def run_params(corr, var_p, var_wn, radial_var, k_mean=1.0, gate_nis=16.3, q_c=0.0):
    """The compiled run's parameters (records.RUN_PARAMS) that the block loops read."""
    return records.record(records.RUN_PARAMS, corr=corr, var_p=var_p, var_wn=var_wn, radial_var=radial_var,
                          k_mean=k_mean, gate_nis=gate_nis, q_c=q_c)


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
    k, c, k_lin, c_lin = 1.1, np.array([0.01, 0.0, -0.02]), 1.05 if nk else 1.1, np.array([0.012, 0.001, -0.018])
    x, x_lin, k_mean = linearised(k, c, k_lin, c_lin, nk)
    A, b, gated, nis, rejected = model.spatial_information(w, w_tcp, r0, v, var_v, var_w, x, x_lin, np.eye(3 + nk),
                                                           run_params(3.0, 2.5e-9, 1e-4, radial_var, k_mean), False)
    args = (k, c, k_lin, c_lin, 3.0, 2.5e-9, 1e-4, radial_var, nk)
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
    k, c, k_lin, c_lin = 1.1, np.array([0.01, -0.02]), 1.05 if nk else 1.1, np.array([0.012, -0.018])
    x, x_lin, k_mean = linearised(k, c, k_lin, c_lin, nk)
    A, b, gated, nis, rejected = model.planar_information(w_n, t_n, r2, v2, var_v, var_w, x, x_lin, 0.5 * np.eye(2 + nk),
                                                          run_params(3.0, 2.5e-9, 1e-4, radial_var, k_mean), False)
    A_ref, b_ref = information(planar_samples(w_n, t_n, r2, v2, var_v, var_w, k, c, k_lin, c_lin, 3.0, 2.5e-9,
                                              1e-4, radial_var, nk), 2 + nk)
    assert_same_information(A, b, A_ref, b_ref)


def test_gate_rejects_an_outlier_once_armed():
    rng = np.random.default_rng(3)
    w, r0, v, var_v, var_w = block(rng)
    w_tcp = np.zeros_like(w)
    c = np.zeros(3)
    v = np.cross(w, r0)                    # consistent with contact at the origin, k = 1
    v[5] += [0.5, 0.0, 0.0]                # one glitch
    args = (w, w_tcp, r0, v, var_v, var_w, c, c)
    prm = run_params(1.0, 2.5e-9, 1e-4, 0.0)
    _, _, gated, nis, rejected = model.spatial_information(*args, np.eye(3) * 1e-12, prm, True)
    assert gated and rejected == 1 and nis[5] > 16.3 and np.all(np.delete(nis, 5) < 16.3)
    _, _, gated, _, rejected = model.spatial_information(*args, np.eye(3) * 0.25, prm, True)
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
        x_new, P_new = linalg.collapsed_update(x, P, A, b, True)
        lam, U = np.linalg.eigh(A)
        good = lam > 1e-12 * lam[-1]
        H = np.sqrt(lam[good])[:, None] * U[:, good].T
        y = (U[:, good].T @ b) / np.sqrt(lam[good])
        S = H @ P @ H.T + np.eye(len(y))
        Kg = P @ H.T @ np.linalg.inv(S)
        np.testing.assert_allclose(x_new, x + Kg @ y, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(P_new, (np.eye(4) - Kg @ H) @ P, rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(P_new, P_new.T, atol=1e-15)
        nis, r = linalg.window_nis(A, b, P)
        assert r == rank and nis == pytest.approx(y @ np.linalg.solve(S, y), rel=1e-7)


def test_sym_eig_matches_numpy_across_wide_ranges():
    rng = np.random.default_rng(5)
    for n in (2, 3, 4):
        for _ in range(50):
            B = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 6, size=(n, 1))
            S = B @ B.T
            lam, V = linalg.sym_eig(S)
            np.testing.assert_allclose(lam, np.linalg.eigvalsh(S), rtol=1e-9, atol=1e-12 * np.abs(S).max())
            np.testing.assert_allclose(V @ np.diag(lam) @ V.T, S, rtol=1e-9, atol=1e-10 * np.abs(S).max())


def test_kernels_divide_by_zero_as_numpy_does():
    """IEEE division, not Python's ZeroDivisionError: a degenerate sample cannot raise in the estimator thread."""
    n = 2
    zeros = np.zeros((n, 3))
    x = np.array([0.0, 0.0, 0.0, 1.0])
    A, b, *_ = model.spatial_information(zeros, zeros, zeros, zeros, np.zeros(n), np.zeros(n), x, x, np.eye(4),
                                         run_params(1.0, 0.0, 0.0, 0.0), False)
    assert A.shape == (4, 4)


def test_jit_compiles_where_numba_cannot_cache():
    """A read-only install without NUMBA_CACHE_DIR: numba refuses cache=True; the loops still compile."""
    ns = {}
    exec("def twice(x):\n    return 2.0 * x\n", ns)        # no source file: nowhere to cache
    with pytest.raises(RuntimeError, match="cannot cache"):
        njit("float64(float64)", cache=True)(ns["twice"])
    assert jit("float64(float64)")(ns["twice"])(1.5) == 3.0


def random_cov(rng, n, scale):
    L = rng.normal(size=(n, n))
    return L @ L.T * scale + 1e-3 * scale * np.eye(n)


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("nk", [0, 1])
def test_block_update_is_the_information_of_the_model_and_its_collapsed_update(planar, nk):
    """World-frame samples in, the updated state out: projection on a skewed plane, the contact's random
    walk over the block's duration, the model's information (numpy, sample by sample) from the rate and
    position paired with each velocity, the update; the current rate and position for the evidence."""
    rng = np.random.default_rng(6)
    w_v, r0, v, var_v, var_w = block(rng)
    origin = np.array([0.3, -0.2, 0.5])
    p_v, dt = origin + r0, rng.uniform(1e-4, 2e-4, len(w_v))
    w, p = w_v + rng.normal(0, 0.01, w_v.shape), p_v + rng.normal(0, 1e-3, p_v.shape)     # at each sample
    d = 2 if planar else 3
    n = np.array([0.2, 1.0, -0.3]) / np.linalg.norm([0.2, 1.0, -0.3])
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    E = np.vstack([e1, np.cross(n, e1)]) if planar else np.eye(3)
    x = np.append(rng.normal(0, 0.05, d), [1.08] * nk)
    x_lin = x + np.append(rng.normal(0, 0.005, d), [0.02] * nk)
    P = random_cov(rng, d + nk, 1e-4)
    q_c, corr, var_p, var_wn, radial_var = 1e-6, 3.0, 2.5e-9, 1e-4, 2.5e-5
    smp = records.contiguous(records.Samples(dt, w, np.zeros_like(w), p, v, w_v, np.zeros_like(w), p_v, var_v, var_w,
                                             np.zeros(0, bool)))
    frame = records.contiguous(records.Frame(E, n, origin))
    prm = run_params(corr, var_p, var_wn, radial_var, k_mean=1.2, q_c=q_c)
    x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r_d, duration = model.block_update(
        x, P, x_lin, smp, 0, len(dt), frame, prm, False, True)
    P_ref = P.copy()
    P_ref[range(d), range(d)] += q_c * dt.sum()
    k, k_lin = (x[d], x_lin[d]) if nk else (1.2, 1.2)          # k held at 1.2 when not a state
    point = (k, x[:d] / k, k_lin, x_lin[:d] / k_lin, corr, var_p, var_wn, radial_var, nk)
    if planar:
        samples = planar_samples(w_v @ n, np.zeros(len(w)), r0 @ E.T, v @ E.T, var_v, var_w, *point)
        np.testing.assert_allclose(w_d[:, 0], w @ n, rtol=1e-12)
    else:
        samples = spatial_samples(w_v, np.zeros_like(w), r0, v, var_v, var_w, *point)
        np.testing.assert_allclose(w_d, w, rtol=1e-12)
    A_ref, b_ref = information(samples, d + nk)
    assert_same_information(A, b, A_ref, b_ref)
    np.testing.assert_allclose(r_d, (p - origin) @ E.T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(P_prior, P_ref, rtol=1e-12)
    assert duration == pytest.approx(dt.sum(), rel=1e-12)
    x_ref, P_new_ref = linalg.collapsed_update(x, P_ref, A_ref, b_ref, True)
    np.testing.assert_allclose(x_new, x_ref, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(P_new, P_new_ref, rtol=1e-7, atol=1e-15)
    assert not gated and rejected == 0


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("z", [None, 1.0, 3.4, 5.0])
@pytest.mark.parametrize("k_mean", [1.0, 1.16])
def test_report_state_matches_numpy(planar, z, k_mean):
    """Without eta (None), scheduled (z = 1 sigma of evidence against eta's prior mean k_mean), half
    blended (3.4) and free (5)."""
    rng = np.random.default_rng(7)
    d = 2 if planar else 3
    origin = np.array([0.3, -0.2, 0.5])
    E = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) if planar else np.eye(3)
    along = (0.25 * np.outer([0.0, 1.0, 0.0], [0.0, 1.0, 0.0])).ravel() if planar else np.zeros(9)
    k_prior_var, r_last = 0.0625, rng.normal(0, 0.1, d)
    if z is None:
        x, P = rng.normal(0, 0.1, d), random_cov(rng, d, 1e-5)
    else:
        P = random_cov(rng, d + 1, 1e-5)
        P[d, :d] = P[:d, d] = 0.3 * np.sqrt(P[d, d] * P.diagonal()[:d])
        info = 1.0 / P[d, d] - 1.0 / k_prior_var
        k_data = k_mean + z / np.sqrt(info)              # the data reject k = k_mean by z sigma
        x = np.append(rng.normal(0, 0.1, d), P[d, d] * (k_data * info + k_mean / k_prior_var))
        assert report.eta_evidence(x[d], P[d, d], k_mean, k_prior_var) == pytest.approx((k_data, z), rel=1e-9)
    wgt = report.eta_weight(x[d], P[d, d], k_mean, k_prior_var, 3.0) if z is not None else 0.0
    assert wgt == (0.0 if z in (None, 1.0) else pytest.approx(min(max(z - 3.0, 0.0), 1.0)))
    p, rep, stat = report.report_state(x, P, d, 1.7, r_last, 0.0025, k_mean, k_prior_var, 3.0, E, origin, along)
    c_ref, rep_ref, stat_ref = reference.report(x, P, d, 1.7, r_last, 0.0025, k_mean, wgt)
    np.testing.assert_allclose(p, origin + c_ref @ E, rtol=1e-12)
    np.testing.assert_allclose(rep, E.T @ rep_ref @ E + along.reshape(3, 3), rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(stat, E.T @ stat_ref @ E + along.reshape(3, 3), rtol=1e-9, atol=1e-18)


@pytest.mark.parametrize("planar", [False, True])
def test_report_states_are_report_state_row_by_row_to_the_last_bit(planar):
    """The one-call report of a run's outputs (ekf's advance) is report_state of each, bit for bit:
    scheduled, blended and free rows, and consistency ratios under 1 (taken as 1)."""
    rng = np.random.default_rng(11)
    d, m = (2 if planar else 3), 6
    origin = np.array([0.3, -0.2, 0.5])
    E = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) if planar else np.eye(3)
    along = (0.25 * np.outer([0.0, 1.0, 0.0], [0.0, 1.0, 0.0])).ravel() if planar else np.zeros(9)
    k_prior_var = 0.0625
    xs, Ps = np.empty((m, d + 1)), np.empty((m, d + 1, d + 1))
    for j, z in enumerate((0.0, 1.0, 3.4, 5.0, 3.6, 0.5)):
        P = random_cov(rng, d + 1, 1e-5)
        info = 1.0 / P[d, d] - 1.0 / k_prior_var
        xs[j] = np.append(rng.normal(0, 0.1, d), P[d, d] * ((1.0 + z / np.sqrt(info)) * info + 1.0 / k_prior_var))
        Ps[j] = P
    rs, ss = rng.normal(0, 0.1, (m, d)), np.column_stack([np.arange(m), np.ones(m), [0.4, 1.0, 1.7, 2.5, 0.9, 3.0]])
    p, rep, stat = np.empty((m, 3)), np.empty((m, 3, 3)), np.empty((m, 3, 3))
    report.report_states(xs, Ps, rs, ss, d, np.array([0.0025, 1.0, k_prior_var, 3.0]), E, origin, along, p, rep, stat)
    for j in range(m):
        one = report.report_state(xs[j], Ps[j], d, max(ss[j, 2], 1.0), rs[j], 0.0025, 1.0, k_prior_var, 3.0, E,
                                  origin, along)
        for got, want in zip((p[j], rep[j], stat[j]), one):
            assert np.array_equal(got, want), (j, got, want)


def test_eta_weight_ignores_an_implausible_eta():
    """Evidence for an eta ratio more than ETA_PRIOR_LIMIT prior sigmas from its mean is the pivot failing."""
    k_prior_var, pkk = 0.0025, 1e-5
    info = 1.0 / pkk - 1.0 / k_prior_var
    for k_data, expected in ((1.15, 1.0), (1.25, 0.0)):   # 3 and 5 prior sigmas off
        x_k = pkk * (k_data * info + 1.0 / k_prior_var)
        assert report.eta_weight(x_k, pkk, 1.0, k_prior_var, 3.0) == expected


@pytest.mark.parametrize("rates", [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.3, 0.2, 0.0]])
def test_rotation_axes_match_numpy(rates):
    """No rotation yet, one axis (a line contact: the covariance projected, 0.5 m along the axis) and two."""
    rng = np.random.default_rng(8)
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    w = (rng.normal(size=(500, 3)) * np.array(rates) + 1e-6 * rng.normal(size=(500, 3))) @ Q.T
    w += 0.5 * np.array(rates) @ Q.T                    # a mean rate to sign the axis
    wwT, w_sum = np.zeros((3, 3)), np.zeros(3)
    report.rate_moments(w, np.full(len(w), 1e-3), wwT, w_sum)
    cov, stat = random_cov(rng, 3, 1e-6), random_cov(rng, 3, 1e-6)
    axis, axes, cov_out, top = report.rotation_axes(wwT, w_sum, len(w), 1e-12, cov, stat, 1e-6, 0.05, 0.25)
    lam, V = np.linalg.eigh(w.T @ w / len(w) - 1e-12 * np.eye(3))
    assert axes == (0 if lam[-1] < 1e-6 else 2 if lam[-2] > 0.05 * lam[-1] else 1)
    if axes == 0:
        assert top == pytest.approx(np.linalg.eigvalsh(stat)[-1], rel=1e-9)
        np.testing.assert_array_equal(cov_out, cov)
        return
    a = V[:, -1] * np.sign(V[:, -1] @ w_sum)
    np.testing.assert_allclose(axis, a, atol=1e-9)
    proj = np.eye(3) - np.outer(a, a)
    assert top == pytest.approx(np.linalg.eigvalsh(proj @ stat @ proj)[-1], rel=1e-9)
    expected = proj @ cov @ proj + 0.25 * np.outer(a, a) if axes == 1 else cov
    np.testing.assert_allclose(cov_out, expected, rtol=1e-9, atol=1e-15)


def test_plane_rotation_matches_numpy():
    rng = np.random.default_rng(9)
    n = np.array([0.2, 1.0, -0.3]) / np.linalg.norm([0.2, 1.0, -0.3])
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    E = np.vstack([e1, np.cross(n, e1)])
    stat = random_cov(rng, 3, 1e-6)
    for w_sum, sign in ((2.0 * n, 1.0), (-0.5 * n + 0.1 * e1, -1.0)):
        s, top = report.plane_rotation(stat, E, n, w_sum)
        assert s == sign and top == pytest.approx(np.linalg.eigvalsh(E @ stat @ E.T)[-1], rel=1e-12)


def test_position_increment_and_residual_match_numpy():
    """The marginal information on (m, k) with the intercept eliminated, and the regression's residual
    at a held k, from the running sums of a random regression."""
    rng = np.random.default_rng(10)
    d, nx, n, var = 3, 4, 40, 2.5e-9
    X = rng.normal(size=(n, d, nx))
    y = rng.normal(size=(n, d)) * 1e-3
    s_x, s_xx, s_xy, s_y = X.sum(0), np.einsum("ija,ijb->ab", X, X), np.einsum("ija,ij->a", X, y), y.sum(0)
    lam, eta = np.eye(nx), np.ones(nx)
    lam0, eta0 = lam.copy(), eta.copy()
    ev = records.contiguous(records.Evidence(records.record(records.EVIDENCE_STATUS), np.zeros(3), np.zeros(d),
                                             np.zeros(d), s_x, s_xx, s_xy, s_y, lam, eta))
    lam, eta = ev.lam, ev.xi
    d_lam, d_eta = evidence.position_increment(ev, n, var)
    lam_ref = (s_xx - s_x.T @ s_x / n) / var
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-12)
    np.testing.assert_allclose(eta, (s_xy - s_x.T @ s_y / n) / var, rtol=1e-12)
    np.testing.assert_allclose(d_lam, lam_ref - lam0, rtol=1e-12)
    np.testing.assert_allclose(d_eta, eta - eta0, rtol=1e-12)
    k = 1.1
    ratio = evidence.position_residual(ev, float((y ** 2).sum()), n, var, k, 8)
    # regression of y - k G on [I (intercept q), -[Theta]x] per sample
    Z = np.concatenate([np.tile(np.eye(d), (n, 1)), X[:, :, :d].reshape(n * d, d)], axis=1)
    resid = (y - k * X[:, :, d]).ravel()
    fit = np.linalg.lstsq(Z, resid, rcond=None)
    rss = float(np.sum((resid - Z @ fit[0]) ** 2))
    assert ratio == pytest.approx(rss / (var * (d * n - d - np.linalg.matrix_rank(Z[:, d:]))), rel=1e-7)
    assert evidence.position_residual(ev, float((y ** 2).sum()), 5, var, k, 8) == 1.0


@pytest.mark.slow
@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("nk", [0, 1])
@pytest.mark.parametrize("chunk", [7, 33, 150])
def test_the_compiled_run_keeps_the_state_of_the_reference_filter(planar, nk, chunk):
    """An arc at 12 cm with 65 Hz positions, gyro outliers, a burst and a slip from 0.5 s: the compiled run
    (ContactKF.update) keeps the state, the counts, the consistency ratio and the slide flag of the
    numpy reference (control/reference.py) after every chunk (chunks of 150 are cut into blocks of
    max_block)."""
    from tecdard.control.estimators.ekf import ContactKF, ContactKfParams
    from tecdard.control.estimators.reference import ReferenceKF
    from tecdard.control.geometry import Plane
    from tecdard.control.measurements import Samples
    rng = np.random.default_rng(11)
    axis = np.array([0.0, -1.0, 0.0])
    t = np.arange(6000) / 6667.0
    ang = 0.02 / 0.12 * t
    lever = np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], axis=1)
    slip = 0.005 * np.maximum(t - 0.5, 0.0)
    p = np.array([0.2, 0.0, 0.5]) + (0.12 + slip)[:, None] * lever
    v = np.cross(0.02 / 0.12 * axis, 0.12 * lever) + (0.005 * (t > 0.5))[:, None] * lever
    held = np.floor(t * 65.0).astype(int)
    first = np.searchsorted(held, np.arange(held[-1] + 1))
    fresh = np.zeros(len(t), bool)
    fresh[first] = True
    pm = (p[first] + rng.normal(0, 5e-5, (len(first), 3)))[held] + v[first][held] * (t - t[first][held])[:, None]
    vm = (v[first] + rng.normal(0, 1e-3, (len(first), 3)))[held]
    w = 0.02 / 0.12 * axis + rng.normal(0, 0.01, (len(t), 3))
    w[200::50] += 0.8                       # outliers for the NIS gate
    w[3000:3200] += 0.6                     # a 30 ms burst: windows the gate mostly rejects
    dt = np.diff(t, prepend=t[0])
    var_v, var_w = np.full(len(t), 1e-6) + (t - t[first][held]) ** 2 * 1e-4, np.zeros(len(t))
    kf = ContactKF(ContactKfParams(estimate_eta=bool(nk)), Plane(axis) if planar else None)
    ref = ReferenceKF(ContactKfParams(estimate_eta=bool(nk)), Plane(axis) if planar else None)
    for f in (kf, ref):
        f.set_correlation(6667.0 / 65.0)
        f.set_eta_prior(1.1, ContactKfParams().eta_rel_std)
        f.start(pm[0], vm[0])
    for k0 in range(0, len(t), chunk):
        sl = slice(k0, k0 + chunk)
        run = Samples.of(dt[sl], w[sl], pm[sl], vm[sl], var_v=var_v[sl], var_w=var_w[sl], fresh=fresh[sl])
        kf.update(run)
        ref.update(run)
        assert (kf.steps, kf.rejected, kf.positions.broken) == (ref.steps, ref.rejected, ref.positions.broken)
        np.testing.assert_allclose(kf.x, ref.x, rtol=REFERENCE_REL_TOL, atol=REFERENCE_REL_TOL * np.abs(ref.x).max())
        np.testing.assert_allclose(kf.P, ref.P, rtol=REFERENCE_REL_TOL, atol=REFERENCE_REL_TOL * np.abs(ref.P).max())
        assert kf.consistency == pytest.approx(ref.consistency, rel=REFERENCE_REL_TOL)
        assert kf.nis == pytest.approx(ref.nis, rel=REFERENCE_REL_TOL)
    assert ref.rejected > 0 and ref.positions.broken and ref.consistency != 1.0   # the rarer branches were taken
