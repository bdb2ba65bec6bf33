"""The estimation benchmark's second source (issue 21): the paper cutter in MuJoCo's rigid-body physics,
checked against the physics it claims (sim/mujoco_source.py)."""
import math

import numpy as np
import pytest

pytest.importorskip("mujoco", reason="the `bench` extra, which `make test` installs")

from control.geometry import quat_to_matrix  # noqa: E402
from sim.mujoco_source import MujocoScenario, generate  # noqa: E402
from tecdard import localize as L  # noqa: E402
from tecdard.config import Config  # noqa: E402
from tecdard.estimation import build_pipeline  # noqa: E402
from tecdard.recording import Recording  # noqa: E402

RATE_TOL = 0.05              # the IMU's relative rate against (handle rate) / eta, steady motion
ANGLE_TOL_DEG = 0.5
END_TOL_M = 0.002            # the hinge at the end of an arc, the onset commanded (measured 0.5 mm at 12 cm)


@pytest.fixture(scope="module")
def arc():
    return generate(MujocoScenario(motion="arc", radius=0.12, speed=0.02, eta=2.0, seed=1))


def steady(fields, truth, t_from=0.7, t_to=1.9):
    t = fields["imu_t"]
    return (t > truth["onset_t"] + t_from - 0.5) & (t < t_to)


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


def test_a_gripper_turning_with_the_handle_leaves_the_fingertip_little_to_see():
    fields, truth = generate(MujocoScenario(motion="arc-turning", seed=1))
    rest = fields["imu_t"] < truth["onset_t"] - 0.05
    bias = fields["gyro"][rest].mean(axis=0)
    w_seen = np.linalg.norm((fields["gyro"][steady(fields, truth)] - bias).mean(axis=0))
    assert abs(w_seen - 0.02 / 0.12) < 0.1 * 0.02 / 0.12          # the IMU turns with the gripper, whole
    R = quat_to_matrix(fields["tcp_quat"])
    turned = math.degrees(math.acos(np.clip((np.trace(R[0].T @ R[-1]) - 1) / 2, -1, 1)))
    assert abs(turned - abs(math.degrees(truth["angle"][-1]))) < 1.0


def test_the_estimator_finds_the_hinge_on_a_mujoco_arc_once_the_onset_is_given(arc):
    fields, truth = arc
    rec = Recording.from_fields(fields)
    pipe = build_pipeline(Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    pipe.begin(float(truth["onset_t"]))           # a commanded onset: the slow start rings nothing
    rows, onset_t, last = L.replay(rec, pipe)
    d = last.p - truth["p_c"]
    a = truth["axis"]
    assert np.linalg.norm(d - (d @ a) * a) < END_TOL_M
