"""Paper-cutter physics against closed-form geometry."""
import numpy as np
import pytest

from tecdard.control.geometry import rotvec_to_matrix
from tecdard.sim.world import HingeParams, HingeWorld

DT_S = 1e-3
HINGE = np.array([0.157, 0.0, 0.487])
AXIS = np.array([0.0, 1.0, 0.0])
P0 = np.array([0.307, 0.0, 0.487])
STILL_BASE_M = 1e-9


def world():
    return HingeWorld(HingeParams(HINGE, AXIS), P0)


def test_following_the_true_arc_leaves_the_base_still():
    w = world()
    starts = 0
    for k in range(1, 1001):
        phi = -np.radians(30.0) * k / 1000          # upwards is a negative turn about +y
        p = HINGE + rotvec_to_matrix(AXIS * phi) @ (P0 - HINGE)
        starts += w.step(p, DT_S)
        assert abs(np.linalg.norm((p - HINGE)[[0, 2]]) - 0.15) < 1e-12   # pivot radius constant
    assert w.base_displacement() < STILL_BASE_M
    assert abs(np.degrees(w.angle) + 30.0) < 1e-9
    assert starts == 1
    assert np.linalg.norm(w.force) < 1e-6


def test_straight_pull_drags_the_base():
    w = world()
    length = np.radians(30.0) * 0.15           # same length as the 30 deg arc
    for k in range(1, 1001):
        w.step(P0 + np.array([0, 0, length * k / 1000]), DT_S)
    friction_n = 0.3 * 2.5 * 9.81
    assert w.base_displacement() > 0.010
    # Quasi-static sliding: the horizontal pull equals friction while dragging.
    f_h = np.linalg.norm(w.force[[0, 1]])
    assert abs(f_h - friction_n) < 0.05 * friction_n


def test_small_misalignment_is_held_by_static_friction():
    w = world()
    for k in range(1, 101):
        w.step(P0 + np.array([0.0005 * k / 100, 0, 0.001 * k / 100]), DT_S)
    assert w.base_displacement() < STILL_BASE_M


def turn_the_handle(w, turn_gripper: bool, deg: float = 30.0, n: int = 1000):
    """Along the true arc; the gripper either holds its orientation or turns with the handle.
    Returns the rate the fingertip felt about the axis at each step."""
    felt = []
    for k in range(1, n + 1):
        phi = -np.radians(deg) * k / n
        p = HINGE + rotvec_to_matrix(AXIS * phi) @ (P0 - HINGE)
        R = rotvec_to_matrix(AXIS * phi) if turn_gripper else np.eye(3)
        w.step(p, DT_S, R)
        felt.append(float(w.object_rate_world() @ AXIS))
    return np.array(felt)


def test_a_held_gripper_twists_the_fingertips_until_the_grasp_slips():
    w = HingeWorld(HingeParams(HINGE, AXIS, twist_stick_deg=10.0), P0, np.eye(3))
    felt = turn_the_handle(w, turn_gripper=False)
    rate = -np.radians(30.0) / (1000 * DT_S)
    assert felt[50:300] == pytest.approx(rate, rel=1e-6)      # sticking: the fingertip turns with the handle
    assert np.abs(felt[400:]).max() < 1e-9                     # slipping: it no longer does
    extra = w.truth()["extra"]
    assert extra["grasp_slip_deg"] == pytest.approx(-20.0, abs=0.05)
    assert extra["grasp_twist_deg"] == pytest.approx(-10.0, abs=1e-6)


def test_a_gripper_turning_with_the_handle_keeps_the_grasp_in_stick():
    w = HingeWorld(HingeParams(HINGE, AXIS, twist_stick_deg=10.0), P0, np.eye(3))
    felt = turn_the_handle(w, turn_gripper=True)
    assert felt[50:] == pytest.approx(-np.radians(30.0), rel=1e-6)   # the gripper's own rate, in full
    assert abs(w.truth()["extra"]["grasp_slip_deg"]) < 1e-9
    assert abs(w.truth()["extra"]["grasp_twist_deg"]) < 1e-6
