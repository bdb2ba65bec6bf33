"""The whole contact pipeline on IMU batches: frames, eta, causal proprioception, the trigger."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from tecdard.control.conditioning import GyroConditioner
from tecdard.control.geometry import (Plane, matrix_to_quat, matrix_to_rotvec, quat_to_matrix, relative_rotvec,
                                      rotvec_to_matrix, signed_angle, unit)
from tecdard.control.onset import OnsetDetector
from tecdard.control.estimators.kernels.report import eta_weight
from tecdard.control.measurements import EtaSchedule
from tecdard.control.proprio import ProprioTrack
from tecdard.control.pipeline import DEFAULT_SATURATION, ContactPipeline, PipelineParams

ODR_HZ = 6667.0
PROPRIO_HZ = 65.0
TOL_M = 3e-3
CLIPPED_EXTRA_ERR_M = 1e-3     # a clipped burst left out costs the estimate at most this


def simulate(R_tcp_imu, R_tool_rate=0.0, eta_true=2.0, noise=5e-3, seed=1, plane=None, method="ekf", options=None,
             on_onset=None):
    """A hinge rotated by a TCP that may itself turn about the hinge axis (rotating gripper); the
    fingertip without lag, and the pipeline told so."""
    rng = np.random.default_rng(seed)
    center, axis = np.array([0.157, 0.0, 0.487]), np.array([0.0, -1.0, 0.0])
    p0 = np.array([0.307, 0.0, 0.487])
    rate = 0.02 / 0.15
    t = np.arange(0, 1.5, 1 / ODR_HZ)
    t_on = 0.5
    s = np.maximum(t - t_on, 0)
    p = center + np.stack([rotvec_to_matrix(axis * rate * si) for si in s]) @ (p0 - center)
    v = np.where((t >= t_on)[:, None], np.cross(rate * axis, p - center), 0.0)
    R0 = rotvec_to_matrix(np.array([np.pi, 0, 0]))
    R_tcp = np.stack([rotvec_to_matrix(axis * R_tool_rate * si) @ R0 for si in s])
    w_tcp = np.where((t >= t_on)[:, None], R_tool_rate * axis, 0.0)
    w_obj = np.where((t >= t_on)[:, None], rate * axis, 0.0)
    w_seen = w_tcp + (w_obj - w_tcp) / eta_true
    R_world_imu = R_tcp @ R_tcp_imu
    gyro = np.einsum("nji,nj->ni", R_world_imu, w_seen) + [0.01, -0.004, 0.007] + rng.normal(0, noise, (len(t), 3))
    accel = np.einsum("nji,nj->ni", R_world_imu, np.tile([0, 0, 9.81], (len(t), 1))) + rng.normal(0, 0.03, (len(t), 3))
    accel[(t >= t_on) & (t < t_on + 0.01)] += [2.0, 0.0, 0.0]
    params = PipelineParams(method=method, plane_normal=plane, fingertip_lag_s=0.0, options=options or {})
    pipe = ContactPipeline(OnsetDetector(0.4, warmup_s=0.05), GyroConditioner(R_tcp_imu, lpf_window=17), params)
    pipe.on_onset = on_onset and (lambda evs: on_onset(pipe, evs))
    events, last, next_proprio = [], None, 0.0
    for k0 in range(0, len(t), 64):
        sl = slice(k0, k0 + 64)
        while next_proprio <= t[sl][-1]:          # proprioception known by the end of the batch
            i = int(next_proprio * ODR_HZ)
            pipe.add_proprio(t[i], p[i] + rng.normal(0, 5e-5, 3), v[i], R_tcp[i], w_tcp[i])
            next_proprio += 1 / PROPRIO_HZ
        ev, est = pipe.process(np.column_stack([t[sl], gyro[sl], accel[sl]]))
        events += ev
        last = est or last
    return events, last, center, axis, t_on, pipe


def in_plane_error(p, center, axis):
    d = p - center
    return float(np.linalg.norm(d - np.dot(d, axis) * axis))


def test_an_estimate_whose_innovations_do_not_fit_is_not_converged():
    """Converged is the in-plane one-sigma under 5 mm, widened by the root NIS ratio where the
    innovations run larger than expected (a soft grasp taking up the motion): the contact_jump
    stop then judges only estimates that both claim and earn their precision."""
    *_, pipe = simulate(np.eye(3), 0.0)
    snap = pipe.estimator.snapshot()
    fits = pipe._estimate(1.0, snap._replace(consistency=0.8))
    assert fits.converged and fits.in_plane_std < 0.005
    ratio = (0.005 / fits.in_plane_std) ** 2 * 1.1          # enough to widen it past 5 mm
    assert not pipe._estimate(1.0, snap._replace(consistency=ratio)).converged


@pytest.mark.parametrize("mount", [[0, 0, 0, 1], [0.3, -0.2, 0.1, 0.9], [0.7071068, 0, 0, 0.7071068]])
@pytest.mark.parametrize("tool_rate", [0.0, 0.05])
def test_pipeline_localises_with_rotated_mount_and_rotating_gripper(mount, tool_rate):
    R_tcp_imu = quat_to_matrix(unit(np.array(mount, float)))
    events, est, center, axis, t_on, pipe = simulate(R_tcp_imu, tool_rate)
    assert [e["kind"] for e in events] == ["contact_onset"]
    assert abs(events[0]["t"] - t_on) < 0.005
    assert in_plane_error(est.p, center, axis) < TOL_M
    assert est.converged
    assert abs(abs(np.dot(est.axis, axis)) - 1.0) < 1e-3
    assert est.std[1] > 0.1            # unobservable along the hinge, and said so
    # Positions are evidence whether the gripper holds its orientation or turns (PositionEvidence),
    # and they fit the rigid pivot.
    assert pipe.estimator.positions.n > 20 and not pipe.estimator.positions.broken


def test_the_onset_is_handed_on_within_its_batch_before_the_episodes_first_estimate():
    """Issue 53 item 2: the daemon publishes an onset as soon as it is decided (EstimatorThread._hand_on), not
    after the episode's first estimates of the rest of the batch have been made."""
    seen = []

    def on_onset(pipe, events):
        seen.append((list(events), pipe.tracking, pipe._t_out))

    events, est, *_ = simulate(np.eye(3), on_onset=on_onset)
    assert len(seen) == 1
    handed, tracking, t_out = seen[0]
    assert handed[-1]["kind"] == "contact_onset" and handed[-1] is next(e for e in events if e["kind"] == "contact_onset")
    assert tracking and t_out == -np.inf          # the episode has begun, and no estimate is made yet
    assert est is not None and est.t > handed[-1]["t"]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["paper-ekf", "svd-diff", "svd-geo"])
def test_pipeline_runs_every_method(method):
    _, est, center, axis, _, _ = simulate(np.eye(3), method=method, plane=np.array([0.0, 1.0, 0.0]))
    assert est.method == method
    assert in_plane_error(est.p, center, axis) < 0.02


def test_eta_mismatch_scales_the_radius():
    """With the wrong eta the estimate moves radially by about the ratio: the fingertip model matters."""
    _, est, center, axis, _, _ = simulate(np.eye(3), eta_true=2.4)
    r_true = 0.15
    r_est = np.linalg.norm((np.array([0.307, 0.0, 0.487]) - est.p)[[0, 2]])
    assert r_est == pytest.approx(r_true * 2.4 / 2.0, rel=0.05)


def test_eta_schedule_interpolates_and_clamps():
    eta = EtaSchedule([(20.0, 2.6), (30.0, 2.0), (40.0, 1.6)])
    assert eta(30.0) == pytest.approx(2.0)
    assert eta(25.0) == pytest.approx(2.3)
    assert eta(10.0) == pytest.approx(2.6) and eta(60.0) == pytest.approx(1.6)


def test_eta_prior_is_centred_between_calibrations_and_one_sided_outside():
    """k = eta_true / eta_scheduled: no known sign between calibrated forces; outside them eta is off the
    clamped schedule the way it falls with force (larger below, smaller above, never below 1)."""
    eta = EtaSchedule([(20.0, 2.6), (30.0, 2.0), (40.0, 1.6)])
    assert eta.prior(30.0, 0.05, 0.02) == (1.0, 0.05)
    assert eta.prior(25.0, 0.05, 0.02) == pytest.approx((1.0, 0.15))
    half_mean, half_std = np.sqrt(2 / np.pi), np.sqrt(1 - 2 / np.pi)      # of a unit half-normal
    assert eta.prior(10.0, 0.05, 0.02) == pytest.approx((1.0 + 0.2 * half_mean, 0.05 + 0.2 * half_std))
    assert eta.prior(50.0, 0.05, 0.02) == pytest.approx((1.0 - 0.2 * half_mean, 0.05 + 0.2 * half_std))
    mean, _ = eta.prior(100.0, 0.05, 0.02)
    assert mean == pytest.approx(0.5 * (1.0 + 1.0 / 1.6))                 # halfway above eta = 1
    assert eta.prior(10.0, 0.05, 0.0) == (1.0, 0.05)


def test_proprio_history_slides_as_a_shifted_window_would():
    """Issue 37: the history's window moves over backing arrays instead of shifting 18 arrays per state;
    every field, lookup and explanation equals the shifting window's, through several wrap-arounds,
    with reported and with derived rates."""
    from tecdard.control.proprio import HISTORY_FIELDS

    class Shifting(ProprioTrack):              # the history as it was: every array shifted by one
        def _slide(self):
            for name in HISTORY_FIELDS:
                arr = getattr(self, name)
                arr[:-1] = arr[1:]

    rng = np.random.default_rng(4)
    for derived in (False, True):
        a, b = ProprioTrack(size=16), Shifting(size=16)
        for i in range(300):
            t = 0.002 * i + 1e-4 * rng.random()
            p = rng.normal(size=3) * 0.01
            R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            v, w = (None, None) if derived else (rng.normal(size=3), rng.normal(size=3))
            for track in (a, b):
                track.add(t, p, v, R, w, float(i))
            if i % 7 == 0:
                ts = np.array([t - 0.02, t - 0.005, t])
                x, y = a.lookup(ts), b.lookup(ts)
                for name in x.__slots__:
                    np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
                np.testing.assert_array_equal(a.explained(ts), b.explained(ts))
        assert a.n == b.n == 16 and a.added == 300
        for name in HISTORY_FIELDS:
            # acc and expl are read only where acc_ok and expl_ok say they were made for their state
            made = getattr(a, name + "_ok", np.ones(16, bool))
            np.testing.assert_array_equal(getattr(a, name)[made], getattr(b, name)[made], err_msg=name)
        np.testing.assert_array_equal(a.acc_ok, b.acc_ok)
        np.testing.assert_array_equal(a.expl_ok, b.expl_ok)
        assert a.acc_ok.any() and a.expl_ok.any()
        assert a.sigma_p_effective() == b.sigma_p_effective() and a.rate_hz() == b.rate_hz()


def test_proprio_lookup_is_causal():
    track = ProprioTrack()
    track.add(0.0, np.zeros(3), np.array([0.1, 0, 0]), np.eye(3), np.zeros(3))
    track.add(0.1, np.array([0.01, 0, 0]), np.array([0.1, 0, 0]), np.eye(3), np.zeros(3))
    track.add(0.2, np.array([0.5, 0, 0]), np.array([5.0, 0, 0]), np.eye(3), np.zeros(3))   # a jump later on
    at = track.lookup(np.array([-0.01, 0.05, 0.15, 0.199]))
    p, ok = at.p, at.ok
    assert list(ok) == [False, True, True, True]
    assert p[1][0] == pytest.approx(0.005) and p[2][0] == pytest.approx(0.015)
    assert p[3][0] == pytest.approx(0.01 + 0.1 * 0.099)      # never sees the sample at 0.2


def test_a_reported_tcp_rate_is_extrapolated_with_its_last_change_for_a_while_only():
    """Between samples a turning gripper's reported rate ramps on (its last change); if proprioception
    stalls, the ramp stops after WDOT_MAX_AGE_S instead of growing without bound."""
    from tecdard.control.proprio import WDOT_MAX_AGE_S
    track = ProprioTrack()
    track.add(0.00, np.zeros(3), np.zeros(3), np.eye(3), np.array([0.0, 0.0, 0.10]))
    track.add(0.01, np.zeros(3), np.zeros(3), np.eye(3), np.array([0.0, 0.0, 0.12]))      # 2 rad/s^2
    w = track.lookup(np.array([0.015, 0.01 + WDOT_MAX_AGE_S, 1.0])).w
    assert w[:, 2] == pytest.approx([0.13, 0.12 + 2.0 * WDOT_MAX_AGE_S, 0.12 + 2.0 * WDOT_MAX_AGE_S])


def test_derived_velocity_when_the_robot_reports_none():
    track = ProprioTrack(sigma_p=1e-4)
    for k in range(5):
        track.add(k * 0.01, np.array([0.02 * k * 0.01, 0, 0]), None, np.eye(3), np.zeros(3))
    at = track.lookup(np.array([0.045]))
    v, var_v = at.v, at.var_v
    assert v[0][0] == pytest.approx(0.02)
    assert var_v[0] == pytest.approx(2 * 1e-4 ** 2 / 0.01 ** 2)


quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1).map(lambda q: unit(np.array(q)))
vecs = st.lists(st.floats(-3, 3, allow_nan=False), min_size=3, max_size=3).map(np.array)


@settings(max_examples=200, deadline=None)
@given(quats)
def test_quaternion_matrix_round_trip(q):
    R = quat_to_matrix(q)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    q2 = matrix_to_quat(R)
    assert np.allclose(q2, q, atol=1e-7) or np.allclose(q2, -q, atol=1e-7)


@settings(max_examples=200, deadline=None)
@given(quats, vecs.filter(lambda v: 1e-3 < np.linalg.norm(v) < 3.0))
def test_float_relative_rotvec_matches_the_numpy_one(q_ref, phi):
    """The simulator's plain-float relative rotation is matrix_to_rotvec(R @ R_ref.T)."""
    R_ref = quat_to_matrix(q_ref)
    R = rotvec_to_matrix(phi) @ R_ref
    assert np.allclose(relative_rotvec(R.tolist(), R_ref.tolist()), matrix_to_rotvec(R @ R_ref.T), atol=1e-7)
    assert np.allclose(relative_rotvec(R.tolist(), R_ref.tolist()), phi, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(vecs.filter(lambda n: np.linalg.norm(n) > 0.1), vecs, st.floats(-3.1, 3.1), st.floats(-2.0, 2.0))
def test_signed_angle_recovers_a_rotation_about_the_axis(axis, a, angle, along):
    """Any a (off the axis), turned by `angle` about the axis and moved along it, is `angle` from a."""
    n = unit(axis)
    if np.linalg.norm(a - (a @ n) * n) < 1e-3:
        return
    b = rotvec_to_matrix(angle * n) @ a + along * n
    assert signed_angle(a, b, n) == pytest.approx(angle, abs=1e-9)
    assert signed_angle(tuple(a), tuple(b), tuple(n)) == signed_angle(a, b, n)


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(quats, quats, vecs, vecs, st.floats(0.5, 5.0))
def test_conditioning_inverts_the_fingertip_model(q_mount, q_tcp, w_tcp, w_obj, eta):
    """For any mount, TCP orientation and rates: recover w_obj from what the gyro sees."""
    R_tcp_imu, R_world_tcp = quat_to_matrix(q_mount), quat_to_matrix(q_tcp)
    gyro = (R_world_tcp @ R_tcp_imu).T @ (w_tcp + (w_obj - w_tcp) / eta)
    out = GyroConditioner(R_tcp_imu).object_rate_world(gyro[None], R_world_tcp, w_tcp[None], eta)
    assert np.allclose(out[0], w_obj, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(vecs.filter(lambda n: np.linalg.norm(n) > 0.1), vecs, vecs)
def test_plane_projection_and_lift(normal, origin, x):
    plane = Plane(normal, origin)
    E = plane.E
    assert np.allclose(E @ E.T, np.eye(2), atol=1e-12)
    assert np.allclose(E @ plane.n, 0, atol=1e-12)
    assert np.dot(np.cross(E[0], E[1]), plane.n) == pytest.approx(1.0)   # right-handed
    x_in = plane.lift(plane.point2(x))
    assert np.allclose(x_in, x - np.dot(x - origin, plane.n) * plane.n, atol=1e-9)
    # w x r in the plane is w_n J r
    w_n, r2 = 0.7, plane.point2(x)
    assert np.allclose(plane.vec2(np.cross(w_n * plane.n, r2 @ E)), w_n * Plane.J @ r2, atol=1e-9)


def idle_pipeline():
    """A pipeline whose trigger never fires, at rest with proprioception up to t = 10 s."""
    pipe = ContactPipeline(OnsetDetector(1e6, warmup_s=0.0), GyroConditioner(np.eye(3)), PipelineParams())
    return pipe


def feed(pipe, t0, t1, gyro, w_tcp=np.zeros(3)):
    t = np.arange(t0, t1, 1 / ODR_HZ)
    for tp in np.arange(t0, t1, 1 / PROPRIO_HZ):
        pipe.add_proprio(tp, np.array([0.3, 0.0, 0.4]), np.zeros(3), np.eye(3), w_tcp)
    accel = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    events = []
    for k0 in range(0, len(t), 128):
        sl = slice(k0, k0 + 128)
        events += pipe.process(np.column_stack([t[sl], np.tile(gyro, (len(t[sl]), 1)), accel[sl]]))[0]
    return events


def test_commanded_onset_starts_at_the_first_sample_at_or_after_the_time():
    pipe = idle_pipeline()
    assert feed(pipe, 0.0, 0.3, np.zeros(3)) == []
    pipe.begin(0.41234)
    (ev,) = feed(pipe, 0.3, 0.6, np.array([0.0, 0.05, 0.0]))
    assert ev["kind"] == "contact_onset" and ev["commanded"] is True
    assert 0.41234 <= ev["t"] < 0.41234 + 1.5 / ODR_HZ
    assert pipe.tracking
    pipe.release()
    assert not pipe.tracking and feed(pipe, 0.6, 0.8, np.zeros(3)) == []     # begin does not outlive its episode


def test_gyro_bias_is_not_learnt_from_a_turning_gripper_nor_a_touching_tool():
    bias = np.array([0.01, -0.004, 0.007])
    pipe = idle_pipeline()
    feed(pipe, 0.0, 1.0, bias)
    assert pipe.cond.bias == pytest.approx(bias, abs=1e-9)
    # the gripper turns about z at 0.5 rad/s (the map task's turn between passes): not bias
    feed(pipe, 1.0, 3.0, bias + [0.0, 0.0, 0.5], w_tcp=np.array([0.0, 0.0, 0.5]))
    assert pipe.cond.bias == pytest.approx(bias, abs=1e-9)
    # the tool touches and turns in the grasp (settling after a touch, backing off): held
    pipe.hold_bias(True)
    feed(pipe, 3.0, 4.0, bias + [0.0, 0.08, 0.0])
    assert pipe.cond.bias == pytest.approx(bias, abs=1e-9)
    # free and still again: the bias is tracked (here a drift of 0.002 rad/s)
    pipe.hold_bias(False)
    feed(pipe, 4.0, 8.0, bias + [0.002, 0.0, 0.0])
    assert pipe.cond.bias[0] == pytest.approx(bias[0] + 0.002, abs=1e-4)


REFERENCE_REL_TOL = 1e-7   # the compiled run against the reference: a collapsed and a stacked update, rounding only


def _troubled_recording(seed=3):
    """A 12 cm arc with what the filter's rarer branches are for: gyro outliers (the NIS gate), a 30 ms
    burst (windows mostly rejected), and the grasp slipping at 5 mm/s from 0.8 s (the position
    evidence's rigid-body check)."""
    from tecdard.sim.scenarios import Scenario, generate
    fields, truth = generate(Scenario(kind="edge-arc", seed=seed, rest_s=0.2, duration_s=1.2))
    t, on = fields["imu_t"], float(truth["onset_t"])
    fields["gyro"][np.flatnonzero(t > on + 0.05)[::40]] += 0.8
    fields["gyro"][(t > on + 0.30) & (t < on + 0.33)] += 0.6
    lever = fields["tcp_pos"] - truth["p_c"]
    lever /= np.linalg.norm(lever, axis=1)[:, None]
    slide_s = np.maximum(fields["tcp_t"] - (on + 0.8), 0.0)
    fields["tcp_pos"] = fields["tcp_pos"] + 0.005 * slide_s[:, None] * lever
    fields["tcp_vel"] = fields["tcp_vel"] + 0.005 * (slide_s > 0)[:, None] * lever
    return fields


def _replay_estimates(fields, method, plane=True, arc_following=False, chunk_s=0.1, rate_hz=1000.0, max_block=64):
    """Every ContactEstimate of a recording's causal replay by `method`, the filter after it, and the
    largest weight of the free-eta estimate in its reports."""
    from tecdard.config import Config
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.replay import replay
    from tecdard.recording.format import Recording
    rec = Recording.from_fields(fields)
    pipe = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz, method=method,
        plane_normal=rec.plane_normal if plane else None)
    pipe.estimator.params.max_block = max_block
    pipe.set_arc_following(arc_following)
    estimates, weights = [], []
    process_all = pipe.process_all

    def collect(batch, force_output=False):
        events, found = process_all(batch, force_output)
        estimates.extend(found)
        est = pipe.estimator
        weights.append(eta_weight(float(est.x[est.d]), float(est.P[est.d, est.d]), est.k_prior_mean,
                                  est.k_prior_var, est.params.eta_test_sigma))
        return events, found
    pipe.process_all = collect
    replay(rec, pipe, rate_hz, chunk_s)
    return estimates, pipe.estimator, max(weights)


def _scenario(**kw):
    from tecdard.sim.scenarios import Scenario, generate
    return generate(Scenario(**{"seed": 3, "rest_s": 0.2, "duration_s": 0.6, **kw}))[0]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["arc", "arc-3d-following", "pen", "hinge", "eta-blend", "troubled",
                                  "troubled-3d", "troubled-long-blocks"])
def test_the_compiled_run_equals_the_reference_filter(case):
    """`ekf` (ContactKF, compiled: each block's samples collapsed to one measurement) gives the
    estimates of `ekf-reference` (control/reference.py: numpy, the block's samples stacked into one
    filterpy-shaped update): the model is what the reference says. Every branch is taken: planar and
    3D, the arc follower's radial distrust, a turning gripper, eta's blend, the NIS gate, the slip
    that breaks the position evidence, a window's gated NIS outgrowing its buffer."""
    make, kw, expect = {
        "arc": (lambda: _scenario(kind="edge-arc"), {}, ""),
        # 3D, the radial distrust of arc following, batches that are no multiple of the output period
        "arc-3d-following": (lambda: _scenario(kind="edge-arc"),
                             dict(plane=False, arc_following=True, chunk_s=0.013), ""),
        "pen": (lambda: _scenario(kind="point-circle"), dict(plane=False, chunk_s=0.05), ""),
        # the gripper turns: its rate in the model and in the position evidence, which pins eta
        "hinge": (lambda: _scenario(kind="hinge"), {}, "blend"),
        # 15 N, calibrated at 30 N: eta's prior leans, and the data pull the free-eta estimate in
        "eta-blend": (lambda: _scenario(kind="edge-arc", grip_force=15.0, duration_s=1.2), {}, "blend"),
        "troubled": (_troubled_recording, {}, "gate slip"),
        "troubled-3d": (_troubled_recording, dict(plane=False, chunk_s=0.007), "gate slip"),
        # 10 Hz outputs in blocks of 512: a window's gated NIS outgrows its first buffer
        "troubled-long-blocks": (_troubled_recording, dict(rate_hz=10.0, max_block=512), "gate slip grow"),
    }[case]
    fields = make()
    compiled, kf, weight = _replay_estimates(fields, "ekf", **kw)
    reference, ref, _ = _replay_estimates(fields, "ekf-reference", **kw)
    assert len(compiled) == len(reference) > 5
    assert (kf.steps, kf.rejected) == (ref.steps, ref.rejected)
    assert kf.positions.broken == ref.positions.broken
    assert ("gate" in expect) == (kf.rejected > 0)
    assert ("slip" in expect) == kf.positions.broken
    assert ("blend" in expect) == (weight > 0)
    assert ("grow" in expect) == (len(kf._gated) > 256)
    for a, b in zip(compiled, reference):
        assert a.t == b.t and a.steps == b.steps and a.converged == b.converged
        assert (a.axis is None) == (b.axis is None)
        for name in ("p", "std", "cov", "axis", "nis", "in_plane_std", "angle_rad", "nis_ratio"):
            x, y = getattr(a, name), getattr(b, name)
            if x is not None:
                np.testing.assert_allclose(x, y, rtol=REFERENCE_REL_TOL, atol=1e-12, err_msg=f"{name} at {a.t}")


@pytest.mark.parametrize("plane", [True, False])
def test_one_compiled_call_per_batch_equals_one_per_segment(monkeypatch, plane):
    """ContactKF.advance runs a batch's segments in one compiled call (kernels.ekf_segments); the
    estimates are those of one `update` per segment (ContactEstimator.advance) bit for bit, through
    the gate and the slip that breaks the position evidence mid-batch (after which the segments
    distrust the velocity along the lever arm)."""
    from tecdard.control.estimators.base import ContactEstimator
    from tecdard.control.estimators.ekf import ContactKF
    fields = _troubled_recording()
    kw = dict(plane=plane, chunk_s=0.1 if plane else 0.007)
    batched, kf, _ = _replay_estimates(fields, "ekf", **kw)
    monkeypatch.setattr(ContactKF, "advance", ContactEstimator.advance)
    segmented, kf2, _ = _replay_estimates(fields, "ekf", **kw)
    assert kf.positions.broken and kf.rejected > 0
    assert len(batched) == len(segmented) > 100
    for a, b in zip(batched, segmented):
        assert (a.t, a.steps, a.nis, a.nis_ratio, a.angle_rad) == (b.t, b.steps, b.nis, b.nis_ratio, b.angle_rad)
        assert np.array_equal(a.p, b.p) and np.array_equal(a.cov, b.cov)


def test_samples_clipped_at_full_scale_are_left_out_and_counted():
    """Issue 16: a clipped gyro sample is no measurement. Mid-episode, 15 ms of a chip at full scale
    leave the estimate where it was without them (every filtered sample whose window holds a clipped
    one is left out), and the estimate says how many were clipped; taken as data they ruin it."""
    from tecdard.control.geometry import quat_to_matrix
    from tecdard.sim.scenarios import Scenario, generate
    from tecdard.config import Config
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.replay import replay
    from tecdard.recording.format import Recording

    fields, truth = generate(Scenario(kind="edge-arc", seed=4, duration_s=0.8))
    rec = Recording.from_fields(fields)

    def final(rec, limits=None):
        pipe = ContactPipeline.from_config(
            Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
            plane_normal=rec.plane_normal)
        if limits is not None:
            pipe.set_saturation(*limits)
        _, _, last = replay(rec, pipe)
        d = last.p - truth["p_c"]
        return float(np.linalg.norm(d - np.dot(d, truth["axis"]) * truth["axis"])), last

    clean_err, clean = final(rec)
    assert clean.saturated == 0
    burst = (rec.imu_t > float(truth["onset_t"]) + 0.2) & (rec.imu_t < float(truth["onset_t"]) + 0.215)
    g_sat, a_sat = DEFAULT_SATURATION
    rec.gyro[burst] = [g_sat + 1e-6, -g_sat - 1e-6, g_sat + 1e-6]        # what the chip reports clipped
    err, last = final(rec)
    assert last.saturated == int(burst.sum()) > 50
    assert err < clean_err + CLIPPED_EXTRA_ERR_M, (err, clean_err)
    naive_err, naive = final(rec, limits=(np.inf, np.inf))              # without the check
    assert naive.saturated == 0 and naive_err > 10 * max(err, 1e-3), (naive_err, err)


def test_the_tcp_position_noise_is_measured_and_the_config_is_its_floor():
    """A rig's TCP can be ten times noisier than the configured encoder grade (the paper's 0.5 mm):
    the noise is measured from the positions' second differences, through a steady motion."""
    from tecdard.control.proprio import ProprioTrack
    rng = np.random.default_rng(3)
    for true_sigma, expected in ((5e-4, 5e-4), (1e-5, 5e-5)):      # noisier than configured; quieter: the floor
        track = ProprioTrack(sigma_p=5e-5)
        for k in range(200):
            t = k / 65.0
            p = np.array([0.3 + 0.02 * t, 0.0, 0.4 + 0.001 * np.sin(t)]) + rng.normal(0.0, true_sigma, 3)
            track.add(t, p, None, np.eye(3), None)
        assert track.sigma_p_effective() == pytest.approx(expected, rel=0.15)


def test_rate_history_means_a_span_and_counts_what_came_before_the_episode():
    """The mean over [t0, t1] of the rates stored (cumulative sums), the part before the episode's start
    as the rate given for it, one sample per period; a span in a gap takes the nearest rate."""
    from tecdard.control.measurements import RateHistory
    h = RateHistory()
    h.start(1.0)
    t = 1.0 + np.arange(100) * 1e-3
    w = np.column_stack([t, 2 * t, np.zeros_like(t)])
    h.add(t[:60], w[:60])
    h.add(t[70:], w[70:])                      # 60-69 left out (clipped)
    before = np.tile([9.0, 9.0, 9.0], (3, 1))
    mean, n = h.mean(np.array([1.010, 0.995, 1.0615]), np.array([1.020, 1.0045, 1.0635]), before, 1e-3)
    np.testing.assert_allclose(mean[0], [1.015, 2.03, 0.0], rtol=1e-12)
    assert n[0] == 11
    # 0.995-1.0045: 5 samples before the start (the rate given) and 5 stored (1.000-1.004)
    assert n[1] == 10
    np.testing.assert_allclose(mean[1], (5 * before[1] + w[:5].sum(axis=0)) / 10, rtol=1e-12)
    assert n[2] == 1                           # in the gap: the nearest stored rate after it
    np.testing.assert_allclose(mean[2], w[70], rtol=1e-12)


def test_the_tcp_rate_is_interpolated_where_it_belongs_and_extrapolated_past_the_newest():
    """Rates derived from orientations belong to the middle of their interval: between those times the
    rate is interpolated; past the newest, extrapolated with the last change (at most WDOT_MAX_AGE_S)."""
    from tecdard.control.proprio import WDOT_MAX_AGE_S
    track = ProprioTrack()
    axis = np.array([0.0, 0.0, 1.0])
    for k in range(6):                          # the rate ramps at 1 rad/s^2, sampled every 10 ms
        t = 0.01 * k
        track.add(t, np.zeros(3), np.zeros(3), rotvec_to_matrix(axis * 0.5 * t ** 2), None)
    w = track.rate_at(np.array([0.03, 0.05, 0.06, 0.5]))
    # derived rates are mean rates over each interval, at its middle (the newest at 45 ms): w(t) = t
    # there, in between, and a little past the newest; far past it the change stops after WDOT_MAX_AGE_S
    np.testing.assert_allclose(w[:3, 2], [0.03, 0.05, 0.06], rtol=1e-6)
    np.testing.assert_allclose(w[3, 2], 0.045 + WDOT_MAX_AGE_S, rtol=1e-6)


@pytest.mark.slow
def test_a_start_from_rest_at_65_hz_is_not_read_as_a_short_lever():
    """The arm starts from rest with proprioception at 65 Hz: for up to 15 ms the newest TCP velocity
    still reads zero while the object already turns. Paired with the object's rate from when it was
    measured (not the newest), it is no evidence of a short lever arm: eta's ratio stays within its
    one-sigma of 1 and the hinge comes out within a millimetre, the gripper turning or not. (Paired
    with the newest rate, eta's ratio went to 0.70 +- 0.04 and the hinge 2-9 mm off.)"""
    for tool_rate in (0.0, 0.05):
        _, est, center, axis, _, pipe = simulate(np.eye(3), tool_rate, noise=0.0)
        kf = pipe.estimator
        assert abs(kf.x[-1] - 1.0) < np.sqrt(kf.P[-1, -1]), (tool_rate, kf.x[-1])
        assert in_plane_error(est.p, center, axis) < 1e-3


def test_the_idle_passes_shortcuts_equal_what_they_stand_for():
    """Issue 37: the idle pass's cheaper forms give the general ones' numbers to the last digit: the
    moving mean as slices once its history is full (against the per-window form, from an empty
    history on, batch after batch), numpy's mean without its wrapper, and the one-time rate lookup
    (ProprioTrack.rate_held) against lookup's."""
    from tecdard.control.conditioning import mean0, moving_mean

    rng = np.random.default_rng(11)
    for w in (1, 2, 7, 33):
        hist, ref_hist = np.zeros((0, 3)), np.zeros((0, 3))
        for n in (1, 3, 40, 67, 5):
            x = rng.normal(size=(n, 3))
            out, hist = moving_mean(hist, x, w)
            ext = np.concatenate([ref_hist, x])
            c = np.cumsum(np.concatenate([np.zeros((1, 3)), ext]), axis=0)
            idx = np.arange(len(ref_hist) + 1, len(ext) + 1)
            lo = np.maximum(idx - w, 0)
            np.testing.assert_array_equal(out, (c[idx] - c[lo]) / (idx - lo)[:, None])
            ref_hist = ext[-(w - 1):] if w > 1 else ext[:0]
            np.testing.assert_array_equal(hist, ref_hist)
        batch = rng.normal(size=(67, 7))
        np.testing.assert_array_equal(mean0(batch[:, 1:4]), batch[:, 1:4].mean(axis=0))

    track = ProprioTrack(size=16)
    assert track.rate_held(0.0) is None
    for i in range(40):
        w = rng.normal(size=3) if i % 2 else None
        track.add(0.002 * i, rng.normal(size=3), None, np.linalg.qr(rng.normal(size=(3, 3)))[0], w)
        for t in (0.002 * i - 0.003, 0.002 * i, 0.002 * i + 0.001, 0.002 * i + 0.2):
            held = track.rate_held(t)
            at = track.lookup(np.array([t]))
            if at.ok[0]:
                np.testing.assert_array_equal(held, at.w[0])
            else:
                assert held is None
