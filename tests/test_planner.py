"""Ruckig ownership: re-planning towards moving targets, braking, named errors."""
import numpy as np
import pytest

from control.planner import CartesianPlanner, PlannerError

TICK_S = 0.02


def test_reaches_target_within_limits():
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.reset(np.zeros(3), speed=0.02)
    target = np.array([0.01, -0.02, 0.005])
    prev_v = np.zeros(3)
    for _ in range(200):
        p, v = pl.step(target)
        assert np.all(np.abs(v) <= 0.02 + 1e-9)
        assert np.all(np.abs(v - prev_v) <= 0.5 * TICK_S + 1e-9)
        prev_v = v
    assert np.allclose(p, target, atol=1e-9) and pl.finished and pl.at_rest


def test_target_velocity_direction_is_kept():
    """A target velocity over the per-axis limit is scaled, not clipped axis by axis."""
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.reset(np.zeros(3), speed=0.02)
    direction = np.array([-0.5, 0.0, 0.866])
    for _ in range(100):
        p, v = pl.step(p + 0.005 * direction if _ else 0.005 * direction, 0.03 * direction)
    assert np.allclose(v / np.linalg.norm(v), direction, atol=1e-3)


def test_brake_stops_with_bounded_deceleration():
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.reset(np.zeros(3), v=np.array([0.0, 0.0, 0.03]), speed=0.05)
    speeds = []
    for _ in range(50):
        _, v = pl.brake()
        speeds.append(np.linalg.norm(v))
    assert speeds[-1] < 1e-9 and pl.at_rest
    assert np.all(np.diff(speeds) <= 1e-12)
    assert np.max(-np.diff(speeds)) <= 0.5 * TICK_S + 1e-9


def test_invalid_input_is_a_named_error():
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.reset(np.zeros(3))
    with pytest.raises(PlannerError, match="ruckig: ErrorInvalidInput: .*target position nan"):
        pl.step(np.array([np.nan, 0.0, 0.0]))
