"""The estimation benchmark's second source (issue 21): the paper cutter in MuJoCo's rigid-body physics,
checked against the physics it claims (sim/mujoco_source.py)."""
import math

import numpy as np
import pytest

pytest.importorskip("mujoco", reason="the `bench` extra, which `make test` installs")

from tecdard.control.geometry import quat_to_matrix  # noqa: E402
from tecdard.sim.mujoco_source import MujocoScenario, generate  # noqa: E402
from tecdard.recording import replay as L  # noqa: E402
from tecdard.config import Config  # noqa: E402
from tecdard.control.pipeline import ContactPipeline  # noqa: E402
from tecdard.recording.format import Recording  # noqa: E402

RATE_TOL = 0.05              # the IMU's relative rate against (handle rate) / eta, steady motion
ANGLE_TOL_DEG = 0.5
END_TOL_M = 0.002            # the hinge at the end of an arc, the onset commanded (measured 0.5 mm at 12 cm)
LAG_TOL_S = 0.001            # the fingertip twist's lag against the source's time constant
PUSH_END_TOL_M = 0.007       # a push's hinge at the end, once the slip is no evidence (measured 3.8 mm median at 8 cm)
BLOCK_END_TOL_M = 0.003      # the block's edge at the end (its contacts give a little)
BLOCK_ANGLE_TOL_DEG = 3.0    # the block turns 2 deg more than the arc: the grasp and the contacts give (measured)
EARLY_TOL_M = 0.010          # the hinge 30 ms into an arc at 12 cm (issue 21's target; measured 4 mm)
MID_TOL_M = 0.002            # the hinge 100 ms into an arc at 12 cm (measured 0.8 mm; 3.6 mm with the positions unpaired)


@pytest.fixture(scope="module")
def arc():
    return generate(MujocoScenario(motion="arc", radius=0.12, speed=0.02, eta=2.0, seed=1))


@pytest.fixture(scope="module")
def ongoing():
    return generate(MujocoScenario(motion="ongoing", radius=0.12, seed=1))


def steady(fields, truth, t_from=0.7, t_to=1.9):
    t = fields["imu_t"]
    return (t > truth["onset_t"] + t_from - 0.5) & (t < t_to)


@pytest.mark.slow
def test_the_handle_turns_as_the_arc_commands_and_the_fingertip_sees_one_over_eta(arc):
    fields, truth = arc
    sc = MujocoScenario()
    expected_deg = math.degrees(sc.speed * (sc.move_s - 0.025) / 0.12)       # the 50 ms smooth start (half lost)
    assert abs(abs(math.degrees(truth["angle"][-1])) - expected_deg) < ANGLE_TOL_DEG
    rest = fields["imu_t"] < truth["onset_t"] - 0.05
    bias = fields["gyro"][rest].mean(axis=0)
    w_seen = np.linalg.norm((fields["gyro"][steady(fields, truth)] - bias).mean(axis=0))
    w_handle = 0.02 / 0.12
    assert abs(w_seen - w_handle / 2.0) / (w_handle / 2.0) < RATE_TOL, (w_seen, w_handle / 2)
    # at rest the accelerometer reads the specific force, g upwards, in the IMU's frame, whose z
    # points down with the tool: -g along z
    np.testing.assert_allclose(fields["accel"][rest].mean(axis=0), [0.0, 0.0, -9.80665], atol=0.02)


@pytest.mark.slow
def test_a_gripper_turning_with_the_handle_leaves_the_fingertip_little_to_see():
    fields, truth = generate(MujocoScenario(motion="arc-turning", seed=1))
    rest = fields["imu_t"] < truth["onset_t"] - 0.05
    bias = fields["gyro"][rest].mean(axis=0)
    w_seen = np.linalg.norm((fields["gyro"][steady(fields, truth)] - bias).mean(axis=0))
    assert abs(w_seen - 0.02 / 0.12) < 0.1 * 0.02 / 0.12          # the IMU turns with the gripper, whole
    R = quat_to_matrix(fields["tcp_quat"])
    turned = math.degrees(math.acos(np.clip((np.trace(R[0].T @ R[-1]) - 1) / 2, -1, 1)))
    assert abs(turned - abs(math.degrees(truth["angle"][-1]))) < 1.0


@pytest.mark.slow
def test_the_estimator_finds_the_hinge_on_a_mujoco_arc_once_the_onset_is_given(arc):
    fields, truth = arc
    rec = Recording.from_fields(fields)
    pipe = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    pipe.begin(float(truth["onset_t"]))           # a commanded onset: the slow start rings nothing
    rows, onset_t, last = L.replay(rec, pipe)
    d = last.p - truth["p_c"]
    a = truth["axis"]
    assert np.linalg.norm(d - (d @ a) * a) < END_TOL_M


def _twist_lag_s(fields, truth):
    """The lag (s) of the fingertip's measured twist behind the handle's, by least squares over shifts:
    eta times the IMU's rate (bias removed) against the handle's rate, both about the hinge, over the
    smooth start (the rates change)."""
    t = fields["imu_t"]
    rest = t < truth["onset_t"] - 0.05
    g = (fields["gyro"] - fields["gyro"][rest].mean(axis=0)) @ quat_to_matrix(fields["tcp_quat"][0]).T
    w_imu = g @ truth["axis"]
    w_handle = np.gradient(truth["angle"], truth["angle_t"])
    win = np.flatnonzero((t > truth["onset_t"]) & (t < truth["onset_t"] + 0.1))
    w_imu = w_imu * np.sign(np.mean(w_imu[win]) * np.mean(w_handle[win]))
    shifts = np.arange(0, 60)
    cost = [np.sum((2.0 * w_imu[win + s] - w_handle[win]) ** 2) for s in shifts]
    return float(shifts[int(np.argmin(cost))] * (t[1] - t[0]))


@pytest.mark.slow
@pytest.mark.parametrize("lag_s", [0.0, 0.004])
def test_the_fingertip_twist_lags_the_handle_by_its_time_constant(lag_s):
    """The silicone's damping on the IMU body: eta x the IMU's rate follows the handle's rate
    `lag_tau_s` later (the handle itself follows the arm within 0.3 ms)."""
    fields, truth = generate(MujocoScenario(motion="arc", lag_tau_s=lag_s, seed=2, tcp_noise=0.0))
    lag = _twist_lag_s(fields, truth)
    assert abs(lag - lag_s) < LAG_TOL_S, lag


def _replay(fields, truth, **estimator):
    """(rows, last estimate) of `ekf` over the recording from its true onset, commanded."""
    rec = Recording.from_fields(fields)
    pipe = ContactPipeline.from_config(
        Config({"estimator": estimator}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    pipe.begin(float(truth["onset_t"]))
    rows, _, last = L.replay(rec, pipe)
    return rows, last


def _error_at(fields, truth, horizon_s, **estimator):
    rows, _ = _replay(fields, truth, **estimator)
    i = min(int(np.searchsorted(rows[:, 0] - float(truth["onset_t"]), horizon_s)), len(rows) - 1)
    d = rows[i, 1:4] - truth["p_c"]
    a = truth["axis"]
    return float(np.linalg.norm(d - (d @ a) * a))


@pytest.mark.slow
def test_the_fingertip_lag_is_compensated_within_the_first_30_ms(arc):
    """Issue 21's early horizon: at 30 ms the arm is still speeding up, and a twist read 3 ms late
    puts the hinge ~20 mm off at 12 cm. With the fingertip's lag (estimator.fingertip_lag_s, the
    source's 3 ms) the estimate is within EARLY_TOL_M."""
    fields, truth = arc
    lagged = _error_at(fields, truth, 0.03, fingertip_lag_s=0.003)
    ignored = _error_at(fields, truth, 0.03, fingertip_lag_s=0.0)
    assert lagged < EARLY_TOL_M < ignored, (lagged, ignored)


@pytest.mark.slow
def test_a_pen_on_its_tip_is_found_in_3d_once_its_top_has_circled():
    """The point contact: a 9 cm pen on its tip, its top circled (2 cm, 3 cm/s) with the gripper held.
    The fingertip twists about ever new axes, more than one eta describes (the twist composes in 3D);
    the displacements then ask for an implausible eta, and stop counting, instead of pulling the
    estimate along (measured: 12-27 mm at the end before, 0.3-0.6 mm now). Before the second axis is
    excited, the report keeps the onset TCP's coordinate along the one axis."""
    fields, truth = generate(MujocoScenario(motion="circle", radius=0.09, speed=0.03, seed=1))
    assert np.all(truth["axis"] == 0.0) and str(truth["kind"]) == "point-circle"
    rec = Recording.from_fields(fields)
    pipe = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    pipe.begin(float(truth["onset_t"]))
    ests = []
    L.replay(rec, pipe, on_estimate=ests.append)
    assert np.linalg.norm(ests[-1].p - truth["p_c"]) < END_TOL_M
    early = [e for e in ests if e.axis is not None and e.std.max() > 0.1]     # one axis so far
    assert early
    for e in early:
        assert abs(float((e.p - e.onset_p_tcp) @ e.axis)) < 1e-9


@pytest.mark.slow
def test_a_block_tipped_on_its_edge_pivots_there_and_the_estimator_finds_the_edge():
    """The block on the table, its bottom edge against the ridge: tipped by an arc about that edge it
    turns as commanded on MuJoCo's contacts, and the estimator finds the edge (measured 0.7-1.0 mm at
    the end, medians of 3 seeds)."""
    fields, truth = generate(MujocoScenario(motion="tilt", radius=0.08, seed=1))
    sc = MujocoScenario(motion="tilt", radius=0.08)
    expected_deg = math.degrees(sc.speed * (sc.move_s - 0.025) / 0.08)
    assert abs(abs(math.degrees(truth["angle"][-1])) - expected_deg) < BLOCK_ANGLE_TOL_DEG
    assert _error_at(fields, truth, np.inf) < BLOCK_END_TOL_M


@pytest.mark.slow
def test_a_push_that_stretches_the_grasp_is_no_evidence_along_the_lever_arm():
    """A straight push along the handle's first tangent: the handle turns on its circle, the TCP runs
    off it, and the grasp stretches along the lever arm. Once the positions show that (the rigid-body
    residual), the velocity along the lever arm is no evidence either (ContactKfSettings.radial_var_now):
    the end error at 8 cm was 8-38 mm with it taken as evidence (median 8.1), 3.8 mm now."""
    fields, truth = generate(MujocoScenario(motion="push", radius=0.08, seed=1))
    with_slip = _error_at(fields, truth, np.inf)
    without = _error_at(fields, truth, np.inf, ekf={"slip_radial_sigma": 0.0})
    assert with_slip < PUSH_END_TOL_M < without, (with_slip, without)


@pytest.mark.slow
def test_the_positions_pair_with_the_twist_read_a_lag_later(arc):
    """The TCP's positions as evidence integrate the object's rotation up to each position. The
    twist the IMU reads now is the object's of a lag ago: paired with the position of now, the
    angle trails the displacement by rate x lag, and the lever arm reads long by lag / t (3.6 mm at
    100 ms at 12 cm). Each position is taken with the twist read a lag after it."""
    fields, truth = arc
    assert _error_at(fields, truth, 0.1, fingertip_lag_s=0.003) < MID_TOL_M


def _relative_twist_deg(fields, truth, t_rel):
    """The IMU's rotation relative to the gripper (the gripper is held), integrated from the onset to
    onset + t_rel, about the hinge, in degrees (bias from the rest before)."""
    t = fields["imu_t"]
    rest = t < truth["onset_t"] - 0.05
    w = (fields["gyro"] - fields["gyro"][rest].mean(axis=0)) @ quat_to_matrix(fields["tcp_quat"][0]).T @ truth["axis"]
    sel = (t >= truth["onset_t"]) & (t < truth["onset_t"] + t_rel)
    return abs(math.degrees(float(np.sum(w[sel]) * (t[1] - t[0]))))


@pytest.mark.slow
def test_a_grasp_that_slips_stops_the_fingertip_twisting_while_the_handle_turns_on():
    """`slip`: the grasp holds until the fingertip's twist torque reaches slip_torque_nm (0.05 N m:
    the pad twisted 0.05 rad at eta 2, 1.4 deg at the IMU), then the handle turns in the grasp: over
    the last half second the handle turns 4.8 deg and the IMU almost not at all."""
    fields, truth = generate(MujocoScenario(motion="slip", seed=1, tcp_noise=0.0))
    early = _relative_twist_deg(fields, truth, 0.15)
    handle_early = abs(math.degrees(np.interp(truth["onset_t"] + 0.15, truth["angle_t"], truth["angle"])))
    assert abs(early - handle_early / 2.0) < 0.2 * handle_early / 2.0       # held: 1/eta of the handle's turn
    twist_mid, twist_end = _relative_twist_deg(fields, truth, 1.0), _relative_twist_deg(fields, truth, 1.5)
    handle_mid, handle_end = (abs(math.degrees(np.interp(truth["onset_t"] + x, truth["angle_t"], truth["angle"])))
                              for x in (1.0, 1.5))
    assert twist_mid < 2.0 and abs(twist_end - twist_mid) < 0.5 and handle_end - handle_mid > 4.0


@pytest.mark.slow
def test_an_ongoing_motion_meets_the_ridge_at_speed_and_the_block_turns_from_there(ongoing):
    """`ongoing`: the arm slides the block along the table into the ridge at 20 mm/s, so the TCP is
    already at speed at the onset (the impact), and the block turns only from then on; the trigger
    fires on the impact (the arm's own start is in the detector's warm-up)."""
    fields, truth = ongoing
    on = float(truth["onset_t"])
    before = (fields["tcp_t"] > on - 0.1) & (fields["tcp_t"] < on - 0.01)
    assert np.all(np.abs(np.linalg.norm(fields["tcp_vel"][before], axis=1) - 0.02) < 0.005)
    assert abs(math.degrees(np.interp(on, truth["angle_t"], truth["angle"]))) < 0.1
    assert abs(math.degrees(np.interp(on + 1.0, truth["angle_t"], truth["angle"]))) > 8.0
    rec = Recording.from_fields(fields)
    pipe = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    _, onset_t, _ = L.replay(rec, pipe)
    assert onset_t is not None and abs(onset_t - on) < 0.03, onset_t - on


@pytest.mark.slow
def test_an_arm_moving_at_the_onset_pushes_through_the_grasp_before_the_pivot_counts(ongoing):
    """`ongoing` at 12 cm: for the first 10-15 ms after the impact the block has not taken up the arm's
    20 mm/s (the TCP's velocity read 7x, 2x, 1.2x the lever arm over the first 5, 10, 15 ms), and
    its displacement then is no pivot's either. With that part of the velocity distrusted as it
    decays and the positions counted from 3 time constants on (IMPACT_TAU_S), the edge is within
    issue 21's 10 mm at 30 ms (measured 4.9 mm; 62 mm before)."""
    fields, truth = ongoing
    assert _error_at(fields, truth, 0.03) < EARLY_TOL_M


@pytest.mark.slow
def test_a_slip_no_filter_models_shows_in_the_reported_uncertainty():
    """`slip` at 12 cm: once the grasp turns on the handle the IMU no longer sees it, and `ekf` reads a
    lever arm that grows with the slip (24.5 mm off at the end, a known limit). Its innovations then
    run far beyond their expected size, and the whole reported covariance, eta's floor included,
    grows with that ratio: the error stays within 3 sigma along the lever arm (26 % of the estimates
    were covered while eta's floor stayed fixed)."""
    fields, truth = generate(MujocoScenario(motion="slip", radius=0.12, seed=1))
    _, last = _replay(fields, truth)
    d = last.p - truth["p_c"]
    a = truth["axis"]
    d = d - (d @ a) * a
    u = d / np.linalg.norm(d)
    assert last.nis_ratio > 10.0
    assert np.linalg.norm(d) < 3.0 * math.sqrt(float(u @ last.cov @ u)), (np.linalg.norm(d), u @ last.cov @ u)
