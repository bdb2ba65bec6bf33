"""Contact estimators on synthetic motion with known answers: exact, statistical, gating."""
import numpy as np
import pytest

from control.baselines import BASELINES, make_baseline
from control.ekf import ContactKF, ContactKfParams, PaperEKF
from control.geometry import Plane, rotvec_to_matrix, unit

ODR_HZ = 6667.0
EXACT_TOL_M = 1e-4        # noise-free answers within 0.1 mm
NOISY_TOL_M = 3e-3        # noisy answers within 3 mm
BLOCK = 7                 # samples per update (1 kHz outputs)


def arc(center, axis, p0, rate, t):
    """TCP on a circle about `axis` through `center`: positions and velocities at times t."""
    axis = unit(axis)
    p = center + np.stack([rotvec_to_matrix(axis * rate * ti) for ti in t]) @ (p0 - center)
    return p, np.cross(rate * axis, p - center)


def in_plane_error(p_est, center, axis):
    d = p_est - center
    return float(np.linalg.norm(d - np.dot(d, unit(axis)) * unit(axis)))


def run(est, t, w, p, v):
    est.start(p[0], v[0])
    dt = np.diff(t, prepend=t[0])          # onset sample: no time has passed yet
    out = []
    for k in range(0, len(t), BLOCK):
        sl = slice(k, k + BLOCK)
        est.update(dt[sl], w[sl], p[sl], v[sl])
        out.append((t[sl][-1],) + est.estimate())
    return out


ALL = ["ekf", "paper-ekf"] + list(BASELINES)


def make(method, plane=None):
    if method == "ekf":
        return ContactKF(ContactKfParams(eta_rel_std=0.0), plane)
    if method == "paper-ekf":
        return PaperEKF(plane=plane)
    return make_baseline(method, plane)


@pytest.mark.parametrize("method", ALL)
@pytest.mark.parametrize("axis", [[0, 1, 0], [1, 1, 0.3], [-0.2, 0.5, 0.8]])
@pytest.mark.parametrize("planar", [False, True])
def test_noise_free_arc_gives_the_exact_centre(method, axis, planar):
    """Any plane orientation (skewed planes included), planar and 3D, every method."""
    axis = unit(np.array(axis, float))
    center = np.array([0.4, -0.1, 0.3])
    r0 = unit(np.cross(axis, [0.3, 0.7, 0.1])) * 0.12
    t = np.arange(1500) / ODR_HZ
    p, v = arc(center, axis, center + r0, 0.15, t)
    w = np.tile(0.15 * axis, (len(t), 1))
    est = make(method, Plane(axis) if planar else None)
    p_c, std = run(est, t, w, p, v)[-1][1:]
    assert in_plane_error(p_c, center, axis) < EXACT_TOL_M
    # Along the axis: the TCP's coordinate at onset (the spec's convention for a line contact).
    assert abs(np.dot(p_c - (center + r0), axis)) < EXACT_TOL_M
    if planar:
        assert np.dot(std, np.abs(axis)) > 0.1      # large and honest along the edge


@pytest.mark.parametrize("method", ["ekf", "paper-ekf"])
def test_point_contact_from_circular_probing_in_3d(method):
    """A tool pivoting about its tip while the TCP circles above it: all three coordinates are observable."""
    tip = np.array([0.5, 0.0, 0.05])
    L, a = 0.14, 0.02
    h = np.sqrt(L ** 2 - a ** 2)
    t = np.arange(int(1.0 * ODR_HZ)) / ODR_HZ
    phi = 2 * np.pi * t / 1.0
    d = np.stack([a * np.cos(phi), a * np.sin(phi), np.full_like(phi, h)], axis=1) / L
    dd = np.stack([-a * np.sin(phi), a * np.cos(phi), np.zeros_like(phi)], axis=1) * (2 * np.pi / 1.0) / L
    p, v = tip + L * d, L * dd
    w = np.cross(d, dd)
    p_c, std = run(make(method), t, w, p, v)[-1][1:]
    assert np.linalg.norm(p_c - tip) < 1e-3
    assert np.all(std < 0.05)


def test_noisy_arc_converges_and_its_uncertainty_covers_the_error():
    rng = np.random.default_rng(4)
    axis, center = np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.0, 0.5])
    t = np.arange(int(1.0 * ODR_HZ)) / ODR_HZ
    p, v = arc(center, axis, center + [0.12, 0, 0], 0.02 / 0.12, t)
    covered, n = 0, 0
    for trial in range(5):
        w = 0.02 / 0.12 * axis + rng.normal(0, 0.01, (len(t), 3))
        pm = p + rng.normal(0, 5e-5, p.shape)
        vm = v + rng.normal(0, 1e-3, v.shape)
        out = run(ContactKF(plane=Plane(axis)), t, w, pm, vm)
        for tk, p_c, std in out[30:]:
            err = np.abs(p_c - center)
            covered += np.all(err[[0, 2]] <= 3 * std[[0, 2]])
            n += 1
        assert in_plane_error(out[-1][1], center, axis) < NOISY_TOL_M
    assert covered / n >= 0.9


def test_ekf_gates_a_velocity_glitch():
    axis, center = np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.0, 0.5])
    t = np.arange(3000) / ODR_HZ
    p, v = arc(center, axis, center + [0.12, 0, 0], 0.15, t)
    v = v.copy()
    v[2500] += [3.0, 0.0, 0.0]                  # one sample 3 m/s off
    w = np.tile(0.15 * axis, (len(t), 1))
    est = ContactKF(ContactKfParams(eta_rel_std=0.0))
    out = run(est, t, w, p, v)
    assert est.rejected >= 1
    assert in_plane_error(out[-1][1], center, axis) < EXACT_TOL_M


def test_paper_ekf_covariance_stays_symmetric_positive():
    rng = np.random.default_rng(0)
    axis, center = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0])
    t = np.arange(4000) / ODR_HZ
    p, v = arc(center, axis, center + [0.1, 0, 0], 0.2, t)
    est = PaperEKF()
    run(est, t, 0.2 * axis + rng.normal(0, 0.01, (len(t), 3)), p, v)
    assert np.allclose(est.P, est.P.T)
    assert np.all(np.linalg.eigvalsh(est.P) > 0)
