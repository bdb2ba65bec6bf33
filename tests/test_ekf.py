"""EKF and pipeline on synthetic motion with known answers."""
import numpy as np
import pytest

from control.conditioning import GyroConditioner
from control.ekf import ContactEKF, EkfParams
from control.geometry import quat_to_matrix, rotvec_to_matrix, unit
from control.onset import OnsetDetector
from control.pipeline import ContactPipeline

ODR_HZ = 6667.0
EXACT_TOL_M = 1e-4        # noise-free answers within 0.1 mm
NOISY_TOL_M = 3e-3        # noisy answers within 3 mm


def arc(center, axis, p0, rate, t):
    """TCP on a circle: position and velocity at times t (rotation about `axis` through `center`)."""
    axis = unit(axis)
    R = np.stack([rotvec_to_matrix(axis * rate * ti) for ti in t])
    r0 = p0 - center
    p = center + R @ r0
    v = np.cross(rate * axis, p - center)
    return p, v


def in_plane_error(p_est, center, axis):
    d = p_est - center
    return float(np.linalg.norm(d - np.dot(d, axis) * axis))


@pytest.mark.parametrize("axis", [[0, 1, 0], [0, 0, 1], [1, 1, 0.3], [-0.2, 0.5, 0.8]])
def test_noise_free_arc_recovers_the_centre(axis):
    axis = unit(np.array(axis, float))
    center = np.array([0.4, -0.1, 0.3])
    # Any radius vector perpendicular to the axis.
    r0 = unit(np.cross(axis, [0.3, 0.7, 0.1])) * 0.12
    t = np.arange(2000) / ODR_HZ
    p, v = arc(center, axis, center + r0, 0.15, t)
    ekf = ContactEKF(EkfParams())
    ekf.start(p[0], v[0])
    for k in range(1, len(t)):
        ekf.step(t[k] - t[k - 1], 0.15 * axis, p[k], v[k])
    assert in_plane_error(ekf.p_c, center, axis) < EXACT_TOL_M
    # Along the axis the contact is unobservable: the filter must say so.
    along_var = axis @ ekf.P[6:9, 6:9] @ axis
    perp = unit(r0)
    assert along_var > 100 * (perp @ ekf.P[6:9, 6:9] @ perp)


def test_noisy_arc_converges_with_honest_covariance():
    rng = np.random.default_rng(4)
    axis = np.array([0.0, -1.0, 0.0])
    center = np.array([0.2, 0.0, 0.5])
    t = np.arange(int(1.0 * ODR_HZ)) / ODR_HZ
    p, v = arc(center, axis, center + [0.15, 0, 0], 0.02 / 0.15, t)
    ekf = ContactEKF(EkfParams())
    ekf.start(p[0], v[0])
    for k in range(1, len(t)):
        w = 0.02 / 0.15 * axis + rng.normal(0, 2e-3, 3)
        ekf.step(t[k] - t[k - 1], w, p[k] + rng.normal(0, 5e-5, 3), v[k])
    assert in_plane_error(ekf.p_c, center, axis) < NOISY_TOL_M
    assert np.all(np.isfinite(ekf.P))
    assert np.allclose(ekf.P, ekf.P.T)
    assert np.all(np.linalg.eigvalsh(ekf.P) > 0)


def test_nis_gate_rejects_outliers():
    ekf = ContactEKF(EkfParams(gate_nis=50.0))
    p, v = np.zeros(3), np.array([0.0, 0.0, 0.02])
    ekf.start(p, v, p_c0=np.array([-0.15, 0.0, 0.0]))
    w = np.array([0.0, -0.02 / 0.15, 0.0])
    for _ in range(200):
        ekf.step(1 / ODR_HZ, w, p, v)
    x_before = ekf.x.copy()
    nis = ekf.step(1 / ODR_HZ, w, p, v + np.array([5.0, 0.0, 0.0]))   # a 5 m/s glitch
    assert nis > 50.0
    assert ekf.rejected == 1
    assert np.allclose(ekf.x[6:9], x_before[6:9])


def test_conditioner_separates_gripper_rotation_from_relative_rotation():
    """The gyro sees the gripper's own rotation in full and the relative rotation / eta."""
    eta = 2.0
    R_tcp_imu = quat_to_matrix(np.array([0.3, -0.2, 0.1, 0.9]) / np.linalg.norm([0.3, -0.2, 0.1, 0.9]))
    R_world_tcp = rotvec_to_matrix(np.array([0.4, 0.1, -0.7]))
    w_tcp = np.array([0.05, -0.1, 0.2])           # the robot turns the tool
    w_obj = np.array([0.3, 0.0, -0.1])            # the object turns about its contact
    w_seen_world = w_tcp + (w_obj - w_tcp) / eta
    gyro = (R_world_tcp @ R_tcp_imu).T @ w_seen_world
    cond = GyroConditioner(R_tcp_imu, eta=eta)
    out = cond.object_rate_world(gyro[None, :], R_world_tcp, w_tcp[None, :])
    assert np.allclose(out[0], w_obj, atol=1e-12)


def test_conditioner_lowpass_is_causal_and_continuous_across_batches():
    cond = GyroConditioner(np.eye(3), lpf_window=5)
    x = np.arange(20, dtype=float)[:, None] * np.ones(3)
    whole = GyroConditioner(np.eye(3), lpf_window=5).lowpass(x)
    parts = np.vstack([cond.lowpass(x[:7]), cond.lowpass(x[7:13]), cond.lowpass(x[13:])])
    assert np.allclose(whole, parts)
    # Causal: sample k depends only on samples <= k.
    assert whole[10, 0] == pytest.approx(np.mean(x[6:11, 0]))


def test_onset_detector_fires_on_the_spike_and_not_on_noise():
    rng = np.random.default_rng(0)
    det = OnsetDetector(accel_threshold=0.4, warmup_s=0.05)
    g = np.array([0.0, 0.0, 9.81])
    t = np.arange(0, 0.3, 1 / ODR_HZ)
    quiet = g + rng.normal(0, 0.03, (len(t), 3))
    assert det.process(t, quiet) == -1
    t2 = t[-1] + np.arange(1, 200) / ODR_HZ
    spike = g + rng.normal(0, 0.03, (len(t2), 3))
    spike[57:] += [0.0, 1.5, 0.0]
    assert det.process(t2, spike) == 57
    assert det.process(t2 + 1, spike) == -1          # disarmed until rearm()
    det.rearm()
    assert det.process(t2 + 2, spike) >= 0


def test_pipeline_triggers_then_localises_a_hinge_from_imu_batches():
    """Rest, then an accelerometer spike and a rotation about a hinge: the pipeline finds the hinge."""
    rng = np.random.default_rng(1)
    eta = 2.0
    center, axis = np.array([0.157, 0.0, 0.487]), np.array([0.0, -1.0, 0.0])
    p0 = np.array([0.307, 0.0, 0.487])
    R_world_tcp = rotvec_to_matrix(np.array([np.pi, 0, 0]))     # tool pointing down
    pipe = ContactPipeline(OnsetDetector(0.4, warmup_s=0.05), GyroConditioner(np.eye(3), eta, lpf_window=17),
                           EkfParams())
    rate = 0.02 / 0.15
    bias = np.array([0.01, -0.004, 0.007])
    t_all = np.arange(0, 1.5, 1 / ODR_HZ)
    t_on = 0.5
    moving = t_all >= t_on
    p, v = arc(center, axis, p0, rate, np.maximum(t_all - t_on, 0))
    v[~moving] = 0.0
    w_obj = np.where(moving[:, None], rate * axis, 0.0)
    gyro = (w_obj / eta) @ R_world_tcp + bias + rng.normal(0, 5e-3, (len(t_all), 3))
    accel = np.tile([0.0, 0.0, -9.81], (len(t_all), 1)) + rng.normal(0, 0.03, (len(t_all), 3))
    accel[(t_all >= t_on) & (t_all < t_on + 0.01)] += [2.0, 0.0, 0.0]
    events_all, last = [], None
    for k0 in range(0, len(t_all), 64):
        sl = slice(k0, k0 + 64)
        # Proprioception at 65 Hz, only what is known by the end of the batch.
        for tp in np.arange(0, t_all[sl][-1], 1 / 65.0):
            i = int(tp * ODR_HZ)
            pipe.add_proprio(t_all[i], p[i], v[i], R_world_tcp, np.zeros(3))
        batch = np.column_stack([t_all[sl], gyro[sl], accel[sl]])
        events, est = pipe.process(batch)
        events_all += events
        last = est or last
    assert [e["kind"] for e in events_all] == ["contact_onset"]
    assert abs(events_all[0]["t"] - t_on) < 0.005
    assert in_plane_error(last.p, center, axis) < NOISY_TOL_M
    assert last.converged
    assert abs(abs(np.dot(last.axis, axis)) - 1.0) < 1e-3
