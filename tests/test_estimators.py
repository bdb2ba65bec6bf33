"""Contact estimators on synthetic motion with known answers: exact, statistical, gating."""
import numpy as np
import pytest

from tecdard.control.estimators.baselines import BASELINES, make_baseline
from tecdard.control.estimators.ekf import ContactKF, ContactKfParams
from tecdard.control.estimators.kernels.report import eta_evidence
from tecdard.control.estimators.paper_ekf import PaperEKF
from tecdard.control.estimators.positions import PositionEvidence
from tecdard.control.measurements import Samples
from tecdard.control.geometry import Plane, rotvec_to_matrix, unit

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


def run(est, t, w, p, v, fresh=None):
    est.start(p[0], v[0])
    dt = np.diff(t, prepend=t[0])          # onset sample: no time has passed yet
    out = []
    for k in range(0, len(t), BLOCK):
        sl = slice(k, k + BLOCK)
        est.update(Samples.of(dt[sl], w[sl], p[sl], v[sl], fresh=None if fresh is None else fresh[sl]))
        out.append((t[sl][-1],) + one_sigma(est))
    return out


def one_sigma(est):
    """(p_c, one-sigma per world axis) of the estimator's report, m."""
    p_c, cov, _ = est.report()
    return p_c, np.sqrt(np.maximum(np.diag(cov), 0.0))


def held_proprio(t, p, v, rate_hz, rng, sigma_p=5e-5, sigma_v=1e-3):
    """Proprioception as the pipeline gives it: noisy samples at rate_hz, extrapolated causally to each
    IMU sample (p_j + v_j * age), with `fresh` marking the first IMU sample that sees a new one."""
    j = np.floor(t * rate_hz + 1e-9).astype(int)
    first = np.searchsorted(j, np.arange(j[-1] + 1))
    pm = p[first] + rng.normal(0, sigma_p, (len(first), 3))
    vm = v[first] + rng.normal(0, sigma_v, (len(first), 3))
    age = t - t[first][j]
    fresh = np.zeros(len(t), bool)
    fresh[first] = True
    return pm[j] + vm[j] * age[:, None], vm[j], fresh


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


@pytest.mark.slow
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


@pytest.mark.parametrize("turning", [0.0, 0.5])
@pytest.mark.parametrize("k_true", [1.0, 1.25, 0.85])
@pytest.mark.parametrize("planar", [True, False])
def test_position_evidence_alone_gives_the_exact_centre_and_eta_ratio(planar, k_true, turning):
    """Displacements alone (r = q + k G - Theta x m, m = k c) pin the contact and the eta ratio k (the
    path's curvature against the gyro's angle), the unknown start marginalised; the gyro here reads
    the rate at a scheduled eta that is k_true too small. With the gripper turning at `turning` of
    the object's rate, eta scales only the rest (its term linearised at k_true: the filter's
    estimate)."""
    axis = unit(np.array([0.2, 1.0, -0.3]))
    center = np.array([0.4, -0.1, 0.3])
    r0 = unit(np.cross(axis, [0.3, 0.7, 0.1])) * 0.12
    t = np.arange(3000) / ODR_HZ
    p, _ = arc(center, axis, center + r0, 0.2, t)
    w_tcp = np.tile(turning * 0.2 * axis, (len(t), 1))
    w = w_tcp + (0.2 * axis - w_tcp) / k_true
    fresh = np.zeros(len(t), bool)
    fresh[::100] = True
    origin = p[0]
    plane = Plane(axis) if planar else None
    ev = PositionEvidence(2 if planar else 3, 5e-5)
    dt = np.diff(t, prepend=t[0])
    for k in range(0, len(t), BLOCK):
        sl = slice(k, k + BLOCK)
        if planar:
            ev.add(dt[sl], w[sl] @ axis, (p[sl] - origin) @ plane.E.T, fresh[sl], w_tcp[sl] @ axis, k_true)
        else:
            ev.add(dt[sl], w[sl], p[sl] - origin, fresh[sl], w_tcp[sl], k_true)
    lam, eta = ev.increment()
    x = np.linalg.lstsq(lam, eta, rcond=1e-9)[0]
    m, k_est = x[:-1], x[-1]
    c = m / k_est
    c_world = origin + (c @ plane.E if planar else c)
    assert abs(k_est - k_true) < 1e-3
    assert in_plane_error(c_world, center, axis) < 1e-5     # rectangle-rule integrals at 6.7 kHz
    assert ev.residual_ratio(k_est) < 0.1       # noise-free: nothing left unexplained at the fitted k


@pytest.mark.slow
def test_positions_sharpen_the_estimate_at_low_speed():
    """10 mm/s about an edge at 12 cm, 65 Hz proprioception: velocity noise dominates, positions help."""
    axis, center = np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.0, 0.5])
    t = np.arange(int(1.0 * ODR_HZ)) / ODR_HZ
    rate = 0.01 / 0.12
    p, v = arc(center, axis, center + [0.12, 0, 0], rate, t)
    errs = {True: [], False: []}
    covered, n = 0, 0
    for seed in range(6):
        for use in (True, False):
            rng = np.random.default_rng(seed)
            pm, vm, fresh = held_proprio(t, p, v, 65.0, rng)
            w = rate * axis + rng.normal(0, 0.01, (len(t), 3))
            est = ContactKF(ContactKfParams(use_positions=use), Plane(axis))
            est.corr_samples = ODR_HZ / 65.0
            out = run(est, t, w, pm, vm, fresh)
            errs[use].append(in_plane_error(out[-1][1], center, axis))
            if use:
                for tk, p_c, std in out[30:]:
                    err = np.abs(p_c - center)
                    covered += np.all(err[[0, 2]] <= 3 * std[[0, 2]])
                    n += 1
    assert np.median(errs[True]) < 0.5 * np.median(errs[False])
    assert max(errs[True]) < NOISY_TOL_M
    assert covered / n >= 0.9


def test_positions_are_dropped_when_the_object_slips_in_the_grasp():
    """A slip halfway through (the TCP then creeps along the lever arm) breaks the rigid-body displacement
    model. (A steady creep from onset is indistinguishable from another contact point, to velocities too.)"""
    axis, center = np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.0, 0.5])
    t = np.arange(int(1.0 * ODR_HZ)) / ODR_HZ
    rate = 0.02 / 0.12
    p, v = arc(center, axis, center + [0.12, 0, 0], rate, t)
    lever = (p - center) / np.linalg.norm(p - center, axis=1)[:, None]
    broken = {}
    slipping = t > 0.5
    for slide in (0.0, 0.005):                     # m/s outward along the lever arm, from 0.5 s
        rng = np.random.default_rng(1)
        ps = p + (slide * np.where(slipping, t - 0.5, 0.0))[:, None] * lever
        vs = v + (slide * slipping)[:, None] * lever
        pm, vm, fresh = held_proprio(t, ps, vs, 65.0, rng)
        est = ContactKF(ContactKfParams(), Plane(axis))
        est.corr_samples = ODR_HZ / 65.0
        run(est, t, np.tile(rate * axis, (len(t), 1)) + rng.normal(0, 0.01, (len(t), 3)), pm, vm, fresh)
        broken[slide] = est.positions.broken
    assert broken == {0.0: False, 0.005: True}


ETA_SEEDS = (1, 2, 3)
ETA_MISMATCH_GAIN = 0.6     # the free-eta estimate at least this much nearer than the calibrated one
ETA_NO_HARM_M = 1e-3        # and never farther than the calibrated one by more than this


def _replay_end(kind, grip_force, seed, estimate_eta, **estimator):
    """End error (m, in the plane of rotation) and the filter of one simulated recording through the pipeline;
    `estimator` overrides keys of the config's estimator section."""
    from tecdard.sim.scenarios import Scenario, generate
    from tecdard.config import Config
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.replay import replay
    from tecdard.recording.format import Recording
    from tecdard.control.geometry import quat_to_matrix

    fields, truth = generate(Scenario(kind=kind, radius=0.12, grip_force=grip_force, seed=seed))
    rec = Recording.from_fields(fields)
    cfg = Config({"estimator": {**estimator, "ekf": {"estimate_eta": estimate_eta}}}).section("estimator")
    pipe = ContactPipeline.from_config(
        cfg, quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz, plane_normal=rec.plane_normal)
    rows, _, _ = replay(rec, pipe, 200.0)
    return in_plane_error(rows[-1, 1:4], truth["p_c"], truth["axis"]), pipe.estimator, rows[-1, 4:7]


@pytest.mark.parametrize("grip_force", [20.0, 40.0])
def test_eta_prior_leans_the_way_eta_moves_off_the_calibration(grip_force):
    """eta calibrated at 30 N only, the grasp at 20 or 40 N (true eta 2.5 or 1.7), eta held: the schedule
    clamped at 2.0 puts the contact 18-30 mm off. Eta falls with grip force, so below the calibration it
    is larger and above it smaller; the prior's mean leans that way (EtaSchedule.prior) and the estimate
    is several times nearer, within 3 sigma of what it reports."""
    clamped = [_replay_end("edge-arc", grip_force, s, False, eta_rel_std_per_n=0.0)[0] for s in ETA_SEEDS]
    leaning = []
    for s in ETA_SEEDS:
        err, kf, std = _replay_end("edge-arc", grip_force, s, False)
        assert (kf.k_prior_mean - 1.0) * (30.0 - grip_force) > 0
        assert err < 3 * np.max(std[std < 0.1])
        leaning.append(err)
    assert min(clamped) > 0.015
    assert np.median(leaning) < 0.5 * np.median(clamped)


# A calibration that says eta is flat (2.0 from 10 to 50 N) while the true eta follows grip force:
# between calibrated forces the error has no known sign, and only the data can find it.
FLAT_ETA_TABLE = [[10.0, 2.0], [30.0, 2.0], [50.0, 2.0]]


@pytest.mark.parametrize("grip_force", [20.0, 40.0])
def test_eta_state_learns_a_grip_force_off_the_calibration(grip_force):
    """The grasp at 20 or 40 N (true eta 2.5 or 1.7) under the flat calibration: once the object has turned
    about 9 deg the path's curvature rejects the scheduled eta, by 2.5-4 sigma in a 1 s arc. The eta
    ratio found lies within 3 sigma of the true one; the estimate is never farther than the calibrated
    one, and where the data reject the calibration outright (the free-eta estimate fully blended in) it
    has moved most of the way to the truth. (Below that the blend is partial: over seeds 1-7 the
    median gain is 0.3 at 20 N but none at 40 N, where the evidence stays under 4 sigma.)"""
    fixed = [_replay_end("edge-arc", grip_force, s, False, eta_table=FLAT_ETA_TABLE)[0] for s in ETA_SEEDS]
    free, ks = [], []
    for s in ETA_SEEDS:
        err, kf, _ = _replay_end("edge-arc", grip_force, s, True, eta_table=FLAT_ETA_TABLE)
        free.append(err)
        k_true = {20.0: 2.5, 40.0: 1.7}[grip_force] / 2.0
        assert abs(kf.x[-1] - k_true) < 3 * np.sqrt(kf.P[-1, -1])
        ks.append(kf.eta_weight())
    assert min(fixed) > 0.015                            # the calibrated eta alone: 18-30 mm off
    assert all(e < f + ETA_NO_HARM_M for e, f in zip(free, fixed)), (free, fixed)
    learned = [e / f for e, f, k in zip(free, fixed, ks) if k == 1.0]
    assert learned and max(learned) < ETA_MISMATCH_GAIN, (free, fixed, ks)


def test_eta_state_keeps_the_calibrated_estimate_at_the_calibrated_force():
    """At the calibrated grip force the data never reject eta: the output is the calibrated filter's."""
    for s in ETA_SEEDS:
        e_fixed, _, _ = _replay_end("edge-arc", 30.0, s, False)
        e_free, kf, _ = _replay_end("edge-arc", 30.0, s, True)
        assert kf.eta_weight() == 0.0
        assert e_free == pytest.approx(e_fixed, abs=1e-4)


def test_eta_state_ignores_a_straight_path():
    """An ongoing motion into an edge: the object slides in the grasp and the TCP runs straight, which
    reads as eta -> infinity. That is the rigid pivot failing, not eta: the calibrated estimate stays."""
    for s in ETA_SEEDS:
        _, kf, _ = _replay_end("edge-ongoing", 30.0, s, True)
        k_data, z = eta_evidence(float(kf.x[kf.d]), float(kf.P[kf.d, kf.d]), kf.k_prior_mean, kf.k_prior_var)
        assert k_data < 0.5 and z > kf.params.eta_test_sigma   # the data do reject eta ...
        assert kf.eta_weight() == 0.0                          # ... implausibly far: not used


def _consistency_trace(block, slide_m_s, seed=5):
    """The ekf's smoothed NIS ratio after each block, on a noisy arc (the filter's own noise model);
    from 0.3 s the TCP also slides outwards along the lever arm at slide_m_s (the grasp giving way).
    The converged estimate explains that only by jumping, so its innovations stop fitting."""
    rng = np.random.default_rng(seed)
    axis, center = np.array([0.0, -1.0, 0.0]), np.array([0.2, 0.0, 0.5])
    t = np.arange(int(0.6 * ODR_HZ)) / ODR_HZ
    p, v = arc(center, axis, center + [0.12, 0, 0], 0.02 / 0.12, t)
    w = 0.02 / 0.12 * axis + rng.normal(0, 0.01, (len(t), 3))
    pm = p + rng.normal(0, 5e-5, p.shape)
    vm = v + rng.normal(0, 1e-3, v.shape) + slide_m_s * (t[:, None] > 0.3) * (p - center) / 0.12
    est = ContactKF(plane=Plane(axis))
    est.start(pm[0], vm[0])
    dt = np.diff(t, prepend=t[0])
    trace = []
    for k in range(0, len(t), block):
        sl = slice(k, k + block)
        est.update(Samples.of(dt[sl], w[sl], pm[sl], vm[sl]))
        trace.append((t[sl][-1], est.consistency))
    trace = np.array(trace)
    return trace[(trace[:, 0] > 0.2) & ((trace[:, 0] < 0.3) | (slide_m_s > 0.0)), 1]


@pytest.mark.parametrize("slide_mm_s", [0.0, 3.0, 10.0])
def test_consistency_ratio_does_not_depend_on_the_block_length(slide_mm_s):
    """The divergence statistic: about 1 or below while the model holds, and a coherent model error
    (a slide along the lever arm) reads the same whether the samples come one at a time or in
    blocks of 5 ms, so the daemon's batching cannot move the divergence stop. At 10 mm/s the gate
    rejects nearly every sample, which must not hide the failure."""
    one, blocks = _consistency_trace(1, slide_mm_s * 1e-3), _consistency_trace(33, slide_mm_s * 1e-3)
    if slide_mm_s == 0.0:
        assert 0.3 < np.median(one) < 1.5 and 0.3 < np.median(blocks) < 1.5
        assert max(one.max(), blocks.max()) < 3.0
    else:
        assert np.median(one) > 5.0
        assert abs(np.median(blocks) / np.median(one) - 1.0) < 0.2
