"""The step guard decides a candidate at once when the accelerometer's remainder swings back (issue 48 §3:
an impact's onset within milliseconds): a step the arm takes keeps its sign, through any lightly damped
mode of the arm, for as long as the arm accelerates; a contact's ring reverses within half its period."""
from __future__ import annotations

import numpy as np
import pytest

from tecdard.control.onset_guard import StepGuard

ODR_HZ = 6667.0


class Arm:
    """The arm's states as the guard asks for them: the change of its fitted acceleration after a time
    (m/s^2) and the newest state's stamp, which comes `lag_s` late."""

    def __init__(self, change: float, lag_s: float = 0.008):
        self.change, self.lag_s, self.now = change, lag_s, 0.0

    def accel_change(self, t_c: float) -> tuple[float, float]:
        return self.change, self.now - self.lag_s

    def fit_span_s(self) -> float:
        return 0.016


def _decide(t, x, guard: StepGuard, arm: Arm, t_c: float, allow: float, batch: int,
            past: bool = True) -> tuple[int, float]:
    """Feeds x from the candidate on in batches of `batch` samples, with the remainder before it when
    `past`: (the sample it was decided at, or -1; the time it was decided)."""
    guard.arm = arm
    k_c = int(np.searchsorted(t, t_c))
    guard.start(t_c, allow, guard.past(x[:k_c], k_c, ODR_HZ) if past else None)
    for s in range(int(np.searchsorted(t, t_c)), len(t), batch):
        tb, xb = t[s:s + batch], x[s:s + batch]
        arm.now = float(tb[-1])
        at = guard.decide(tb, np.linalg.norm(xb, axis=1), 0.5, xb)
        if at >= 0:
            return s + at, float(tb[-1])
        if not guard.waiting:
            return -1, float(tb[-1])
    return -1, float(t[-1])


def _ring(t, t0, amp, hz=120.0, tau=0.015):
    s = np.maximum(t - t0, 0.0)
    return np.where(t >= t0, amp * np.exp(-s / tau) * np.sin(2 * np.pi * hz * s), 0.0)


def test_a_contacts_ring_is_decided_at_its_reversal_in_any_batching():
    rng = np.random.default_rng(1)
    t = np.arange(0, 0.1, 1.0 / ODR_HZ)
    u = np.array([0.6, -0.8, 0.0])
    x = _ring(t, 0.05, 2.0)[:, None] * u + 0.02 * rng.standard_normal((len(t), 3))
    allow = 0.6
    t_c = float(t[np.flatnonzero(np.linalg.norm(x, axis=1) > allow)[0]])
    found = set()
    for batch in (1, 8, 67, len(t)):
        guard = StepGuard(lag_s=0.008)
        k, _ = _decide(t, x, guard, Arm(change=0.0), t_c, allow, batch)
        assert guard.decided_t == t_c and guard.reversals == 1
        found.add(k)
    (k,) = found                                          # the same sample whatever the batches
    assert x[k] @ u < -allow and x[k - 1] @ u >= -allow
    # half the ring's period (4.2 ms) after the contact: long before the arm's states (8 ms late, 16 ms fit)
    assert 0.004 <= t[k] - 0.05 <= 0.006


@pytest.mark.parametrize("mode_hz, gain", [(14.0, 0.3), (33.0, 0.3), (33.0, 1.0), (150.0, 1.0)])
def test_a_step_through_a_lightly_damped_mode_is_left_to_the_arms_states(mode_hz, gain):
    """A 1.5 m/s^2 step on top of vibration already there, `gain` of it through a mode (zeta 0.02; 1: the
    whole step, which overshoots it almost twice). A passive mode's step response never falls below
    zero: the step waits for the states (which explain the nominal 0.3; a whole step doubled is past
    what they allow, the older part of the guard's business)."""
    rng = np.random.default_rng(2)
    t = np.arange(0, 0.2, 1.0 / ODR_HZ)
    w, zeta, t0 = 2 * np.pi * mode_hz, 0.02, 0.05
    s = np.maximum(t - t0, 0.0)
    wd = w * np.sqrt(1 - zeta ** 2)
    ring = np.exp(-zeta * w * s) * (np.cos(wd * s) + zeta * w / wd * np.sin(wd * s))
    step = np.where(t >= t0, 1.5 * (1 - gain * ring), 0.0)
    u = np.array([0.0, 0.0, 1.0])
    x = step[:, None] * u + 0.05 * rng.standard_normal((len(t), 3))
    x[:, 2] += 0.1 * np.sin(2 * np.pi * 40.0 * t)           # the servo's dither, there before the step
    allow = 0.6
    t_c = float(t[np.flatnonzero(np.linalg.norm(x, axis=1) > allow)[0]])
    guard = StepGuard(lag_s=0.008)
    k, when = _decide(t, x, guard, Arm(change=1.5), t_c, allow, 8)
    assert guard.reversals == 0
    assert when >= t_c + 0.008 + 0.016                       # decided by the states, once they covered it
    if gain < 1.0:
        assert k == -1 and guard.explained_steps == 1


def test_reversal_off_waits_for_the_states():
    t = np.arange(0, 0.1, 1.0 / ODR_HZ)
    x = _ring(t, 0.05, 2.0)[:, None] * np.array([1.0, 0.0, 0.0])
    t_c = float(t[np.flatnonzero(np.abs(x[:, 0]) > 0.6)[0]])
    guard = StepGuard(lag_s=0.008)
    guard.reversal_s = 0.0
    k, when = _decide(t, x, guard, Arm(change=0.0), t_c, 0.6, 8)
    assert guard.decided_t == t_c and guard.reversals == 0
    assert t[k] >= t_c + 0.008 + 0.016


def test_a_step_on_a_vibrating_arm_is_judged_from_the_vibrations_swing():
    """The servo's dither three times its nominal (40 Hz, 1.7 m/s^2) swings the remainder beyond the
    threshold and back within 6 ms by itself: a 0.5 m/s^2 step the arm takes on it is judged from the
    level and swing of the 25 ms before it, and waits for the states. Judged from zero, it would pass
    for a contact's ring."""
    rng = np.random.default_rng(4)
    t = np.arange(0, 0.2, 1.0 / ODR_HZ)
    u = np.array([1.0, 0.0, 0.0])
    t0 = 0.05 + (160.0 / 360.0) / 40.0                     # as the dither falls through 160 deg
    x = (1.7 * np.sin(2 * np.pi * 40.0 * t) + np.where(t >= t0, 0.5, 0.0))[:, None] * u
    x = x + 0.03 * rng.standard_normal((len(t), 3))
    t_c = float(t[np.flatnonzero((t >= t0) & (np.linalg.norm(x, axis=1) > 0.6))[0]])
    guard = StepGuard(lag_s=0.008)
    k, when = _decide(t, x, guard, Arm(change=0.5), t_c, 0.6, 8)
    assert guard.reversals == 0 and when >= t_c + 0.008 + 0.016
    blind = StepGuard(lag_s=0.008)
    k, _ = _decide(t, x, blind, Arm(change=0.5), t_c, 0.6, 8, past=False)
    assert blind.reversals == 1                              # what the swing is for
