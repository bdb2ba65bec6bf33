"""Ruckig ownership: re-planning towards moving targets, braking, named errors."""
import numpy as np
import pytest

from tecdard.control.planner import MAX_ADVANCE_TICKS, CartesianPlanner, PlannerError

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


# Valid re-plans on which this Ruckig build fails numerically (found by fuzzing re-plans with
# late ticks; pantor/ruckig#160): (current p, v, a, target p, speed cap, minimum duration).
RUCKIG_KNIFE_EDGES = [
    ([0.011814658068259903, 0.006143566382140092, 0.04556597114478244], [0.01, 0.003067565918213409, -0.008704797156921316],
     [0.0, 0.0, 0.03798636413774537], [0.16321175401302596, 0.05264682811569868, -0.0840665147676603], 0.01,
     0.572348030420526),
    ([0.012064492092250525, -0.0003565576834306997, 0.026244434403546166],
     [-0.0025273641322374504, 0.003571749083406619, 0.012799028247729966],
     [0.13915026628232308, 0.40531778787259487, 0.26834626422348495],
     [0.09931742218308653, 0.14199343573164003, -0.060176300396991955], 0.02, 0.31588560762232043),
]


@pytest.mark.parametrize("p, v, a, target, speed, duration", RUCKIG_KNIFE_EDGES)
def test_a_ruckig_calculation_failure_on_valid_input_is_planned_axis_by_axis_for_one_cycle(p, v, a, target, speed,
                                                                                          duration):
    import ruckig
    pl = CartesianPlanner(TICK_S, max_speed=0.05, max_accel=0.5, max_jerk=5.0)
    pl.reset(np.array(p), v=np.array(v), a=np.array(a), speed=speed)
    pl.inp.minimum_duration, pl.inp.target_position = duration, target
    with pytest.raises(ruckig.RuckigError, match="error in step"):
        pl.otg.update(pl.inp, pl.out)           # Ruckig alone fails here
    pl.reset(np.array(p), v=np.array(v), a=np.array(a), speed=speed)
    p1, v1 = pl.step(np.array(target), None, duration)
    assert pl.fallbacks == 1 and np.all(np.abs(v1) <= speed + 1e-12)
    assert np.linalg.norm(p1 - p) < 0.05 * TICK_S            # one cycle's motion at most
    assert pl.inp.synchronization == ruckig.Synchronization.Time and pl.inp.minimum_duration == duration
    for _ in range(5):                                        # and the next cycles plan normally
        pl.step(np.array(target), None, duration)
    assert pl.fallbacks == 1
