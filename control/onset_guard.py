"""The onset trigger's two defences against a real arm (issue 48): the accelerometer's moving noise floor
(NoiseFloor), and the wait for the arm's states that may explain an acceleration step (StepGuard).
control.onset's OnsetDetector holds one of each."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# A real arm's tool vibrates (0.045-0.07 rad/s, and up to a m/s^2, that the joint encoders never see) and a
# tool IMU is noisier than ours: the accelerometer's threshold is at least FLOOR_K times the remainder's
# RMS over the last FLOOR_TAU_S (its moving noise floor), learned while nothing is pending, armed or not,
# so that a trigger fired on a vibrating arm settles and re-arms on that arm's level, not an idle board's.
FLOOR_K = 4.0
FLOOR_TAU_S = 2.0             # the floor forgets this slowly ...
FLOOR_RISE_TAU_S = 0.25       # ... and learns a rising vibration (the joints' harmonics as the arm speeds up) this fast
STEP_RING_TAU_S = 0.5         # an explained step's allowance decays this slowly: a lightly damped arm rings on
# An arm that starts with an acceleration step (a UR's speedL trapezoid, a pendant jog) shows it in the
# IMU at once and in its states only after their latency and the acceleration fit's span. An
# accelerometer onset therefore waits for those states (proprio_lag_s + ProprioTrack.fit_span_s): the
# peak remainder within PEAK_WINDOW_S of the candidate must exceed the threshold plus (1 + swing_accel)
# times the change the states then show of the arm's own acceleration. An impact's peak is sharper than
# any change the arm's states can show over the fit; a step the arm took is as large as the change.
PEAK_WINDOW_S = 0.01
STALE_WAIT_S = 0.05           # states that stop coming: decided this long after they were due, as they stand


@dataclass
class Candidate:
    """An accelerometer onset waiting for the arm's states: its time, the peak remainder within
    PEAK_WINDOW_S of it (m/s^2), and its threshold with the allowances then (m/s^2)."""
    t: float
    peak: float
    allow: float


class NoiseFloor:
    """The accelerometer remainder's moving mean square: learned over FLOOR_RISE_TAU_S when it rises
    and FLOOR_TAU_S when it falls (a cumulative mean at first); the threshold is at least k times its
    root (k = 0: off)."""

    def __init__(self, k: float = 0.0):
        self.k = k
        self.ms = 0.0            # (m/s^2)^2
        self.seen_s = 0.0

    def threshold(self, configured: float) -> float:
        return max(configured, self.k * math.sqrt(self.ms))

    def learn(self, t: np.ndarray, dev: np.ndarray, odr_hz: float) -> None:
        dt = float(t[-1] - t[0]) + 1.0 / odr_hz
        ms = float(np.mean(dev * dev))
        tau = FLOOR_RISE_TAU_S if ms > self.ms else FLOOR_TAU_S
        alpha = max(dt / (self.seen_s + dt), 1.0 - math.exp(-dt / tau))
        self.ms += alpha * (ms - self.ms)
        self.seen_s += dt


class StepGuard:
    """An accelerometer candidate waiting for the arm's states (`arm`: control.proprio.ProprioTrack's
    accel_change and fit_span_s), then decided: an onset dated at the candidate (`decided_t`), or the
    arm's own step (`explained_steps`), whose allowance then decays with STEP_RING_TAU_S (`mask`)."""

    def __init__(self, lag_s: float = 0.0):
        self.lag_s = lag_s                 # how late the states may be stamped (estimator.onset.proprio_lag_s)
        self.arm = None
        self.candidate: Candidate | None = None
        self.decided_t: float | None = None
        self.masked = (0.0, -np.inf)       # the last explained step: (its allowance, m/s^2; when)
        self.explained_steps = 0

    @property
    def waiting(self) -> bool:
        return self.candidate is not None

    def applies(self, explaining: bool, mode: str) -> bool:
        """Whether an accelerometer onset waits: the arm's motion taken off, states to wait for, mode any."""
        return self.lag_s > 0.0 and self.arm is not None and explaining and mode == "any"

    def clear(self) -> None:
        self.candidate = None

    def start(self, t_c: float, allow: float) -> None:
        self.candidate = Candidate(t_c, 0.0, allow)

    def mask(self, t: np.ndarray):
        """What is still allowed of the last step the arm's states explained, decaying with STEP_RING_TAU_S."""
        amp, since = self.masked
        if amp == 0.0 or float(t[-1]) < since:
            return 0.0
        return amp * np.exp(-np.maximum(t - since, 0.0) / STEP_RING_TAU_S)

    def decide(self, t: np.ndarray, dev: np.ndarray | None, swing_accel: float) -> int:
        """The waiting candidate against the arm's states, with this batch's accelerometer remainder
        `dev` (n,): the index of the sample it is decided at (an onset; `decided_t` its time), or -1
        (still waiting, or the arm's own step)."""
        c = self.candidate
        if dev is not None:
            win = (t >= c.t) & (t <= c.t + PEAK_WINDOW_S)
            if win.any():
                c.peak = max(c.peak, float(dev[win].max()))
        change, newest = self.arm.accel_change(c.t)
        due = c.t + self.lag_s + self.arm.fit_span_s()
        last = float(t[-1])
        if (newest < due and last < due + STALE_WAIT_S) or last < c.t + PEAK_WINDOW_S:
            return -1
        self.candidate = None
        explained = (1.0 + swing_accel) * change
        if c.peak > c.allow + explained:
            self.decided_t = c.t
            return min(int(np.searchsorted(t, max(due, float(t[0])))), len(t) - 1)
        self.explained_steps += 1
        self.masked = (explained, last)
        return -1
