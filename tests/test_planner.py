"""Ruckig ownership: re-planning towards moving targets, braking, named errors."""
import numpy as np
import pytest

from control.planner import MAX_ADVANCE_TICKS, CartesianPlanner, PlannerError

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


def test_a_late_tick_advances_the_plan_by_the_time_that_passed():
    """Ticks on time follow the plan period by period; a late tick takes the plan's state at its
    own time, and the tick that catches up advances it by what little time passed since."""
    def cruise(gaps):
        pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
        pl.reset(np.zeros(3), v=np.array([0.02, 0.0, 0.0]), speed=0.02)
        t, out = 0.0, []
        for gap in gaps:
            t += gap
            pl.advance(t)
            out.append((t, pl.position[0], pl.velocity[0]))
            pl.step(np.array([1.0, 0.0, 0.0]), np.array([0.02, 0.0, 0.0]))
        return out

    on_time = cruise([TICK_S] * 6)
    assert [x for _, x, _ in on_time] == pytest.approx([0.02 * TICK_S * k for k in range(6)], abs=1e-12)
    late = cruise([TICK_S, TICK_S, 0.055, 0.005, TICK_S])
    for t, x, v in late:
        assert x == pytest.approx(0.02 * (t - TICK_S), abs=1e-12) and v == pytest.approx(0.02)
    # a stall longer than MAX_ADVANCE_TICKS periods advances the plan by that much only
    stalled = cruise([TICK_S, 1.0])
    assert stalled[1][1] == pytest.approx(0.02 * MAX_ADVANCE_TICKS * TICK_S, abs=1e-12)


def test_a_reset_plan_does_not_advance():
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.advance(0.0)
    pl.reset(np.zeros(3), v=np.array([0.02, 0.0, 0.0]), speed=0.02)
    pl.step(np.array([1.0, 0.0, 0.0]), np.array([0.02, 0.0, 0.0]))
    pl.reset(np.array([0.5, 0.0, 0.0]))
    pl.advance(0.08)
    assert pl.position[0] == 0.5 and pl.velocity[0] == 0.0
