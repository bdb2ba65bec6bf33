"""The onset trigger's three defences against a real arm (issue 48): the accelerometer remainder's
prediction from its own past, which takes the arm's narrow-band vibration off (Predictor), its moving
noise floor (NoiseFloor), and the wait for the arm's states that may explain an acceleration step
(StepGuard). control.onset's OnsetDetector holds one of each."""
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
# ... and, judged on the prediction's error (Predictor), at least FLOOR_K times its RMS over the RECENT_S
# that end RECENT_GAP_S before each sample: a vibration the predictor has not learned yet (the joints'
# harmonics at a new speed) grows over tens of ms and raises its own threshold; an impact rises within
# RECENT_GAP_S, before its own samples count.
RECENT_S = 0.03
RECENT_GAP_S = 0.003
STEP_RING_TAU_S = 0.5         # an explained step's allowance decays this slowly: a lightly damped arm rings on
# An arm that starts with an acceleration step (a UR's speedL trapezoid, a pendant jog) shows it in the
# IMU at once and in its states only after their latency and the acceleration fit's span. An
# accelerometer onset therefore waits for those states (proprio_lag_s + ProprioTrack.fit_span_s): the
# peak remainder within PEAK_WINDOW_S of the candidate must exceed the threshold plus (1 + swing_accel)
# times the change the states then show of the arm's own acceleration. An impact's peak is sharper than
# any change the arm's states can show over the fit; a step the arm took is as large as the change.
PEAK_WINDOW_S = 0.01
STALE_WAIT_S = 0.05           # states that stop coming: decided this long after they were due, as they stand
# ... unless the remainder reverses first: a step the arm takes keeps its sign for as long as the arm
# accelerates (a trapezoid's ramp lasts v/a, tens to hundreds of ms), and no passive mode of the arm turns
# it round, while a contact's ring swings back within half its period. A candidate whose remainder, from
# its level over the REVERSAL_PAST_S before it and along its peak's direction, falls beyond minus its
# threshold, and beyond REVERSAL_SWING_K times the largest swing from that level over that past (the
# arm's vibration: a step plus a vibration no larger never reaches it), within REVERSAL_S is an onset at
# once (estimator.onset.reversal_s; 0: off).
REVERSAL_S = 0.006
REVERSAL_PAST_S = 0.025
REVERSAL_SWING_K = 1.0


@dataclass
class Candidate:
    """An accelerometer onset waiting for the arm's states: its time, the peak remainder within
    PEAK_WINDOW_S of it (m/s^2), and its threshold with the allowances then (m/s^2)."""
    t: float
    peak: float
    allow: float
    views: np.ndarray | None = None     # the peak of each view of the remainder (StepGuard.decide)
    x_peak: np.ndarray | None = None    # the remainder (3,) at its largest since the candidate, m/s^2
    level: np.ndarray | None = None     # the remainder's mean (3,) over the REVERSAL_PAST_S before it, m/s^2
    past: np.ndarray | None = None      # the remainder then, less that mean (m, 3), m/s^2: its swing along
                                        # the peak's direction is the reversal's bar (StepGuard._reversal)


class NoiseFloor:
    """The accelerometer remainder's moving mean square: learned over FLOOR_RISE_TAU_S when it rises
    and FLOOR_TAU_S when it falls (a cumulative mean at first); the threshold is at least k times its
    root (k = 0: off)."""

    def __init__(self, k: float = 0.0):
        self.k = k
        self.ms = 0.0            # (m/s^2)^2
        self.seen_s = 0.0
        self._sq = np.zeros(0)   # the recent squares (recent)

    def restart(self) -> None:
        """What it learned no longer measures the signal it judges (the predictor's first fit)."""
        self.ms, self.seen_s = 0.0, 0.0

    def threshold(self, configured: float) -> float:
        return max(configured, self.k * math.sqrt(self.ms))

    def recent(self, dev: np.ndarray, odr_hz: float) -> np.ndarray:
        """k times dev's RMS over the RECENT_S ending RECENT_GAP_S before each sample (n,), m/s^2; the
        history carries over batches (0 where there is none yet)."""
        w = max(1, int(round(RECENT_S * odr_hz)))
        gap = max(1, int(round(RECENT_GAP_S * odr_hz)))
        full = np.concatenate([self._sq, dev * dev])
        m = len(self._sq)
        self._sq = full[-(w + gap):]
        c = np.concatenate([[0.0], np.cumsum(full)])
        end = np.arange(m, m + len(dev)) - gap + 1        # the window's end (exclusive) in full
        start = np.maximum(end - w, 0)
        end = np.maximum(end, start)
        ms = (c[end] - c[start]) / np.maximum(end - start, 1)
        return self.k * np.sqrt(np.maximum(ms, 0.0))

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
        self.reversal_s = REVERSAL_S       # a candidate that swings back this soon is an onset (estimator.onset.reversal_s)
        self.reversals = 0                 # candidates decided so
        self.commands = None               # control.command_track.CommandTrack: the daemon's own commands, or None
        self.commanded = 0                 # candidates decided at once, the arm's commands steady
        self._past = np.zeros((0, 3))      # the remainder's last REVERSAL_PAST_S (observe)

    @property
    def waiting(self) -> bool:
        return self.candidate is not None

    def applies(self, explaining: bool, mode: str) -> bool:
        """Whether an accelerometer onset waits: the arm's motion taken off, states to wait for, mode any."""
        return self.lag_s > 0.0 and self.arm is not None and explaining and mode == "any"

    def clear(self) -> None:
        self.candidate = None

    def start(self, t_c: float, allow: float, past: np.ndarray | None = None) -> None:
        """A candidate at t_c with its threshold `allow` (m/s^2), and the accelerometer remainder
        before it (m, 3; `past`), whose level and swing its reversal is judged from."""
        c = self.candidate = Candidate(t_c, 0.0, allow)
        if past is not None and len(past):
            c.level = past.mean(axis=0)
            c.past = past - c.level

    def past(self, x: np.ndarray, k: int, odr_hz: float) -> np.ndarray:
        """The remainder over the REVERSAL_PAST_S before sample k of the batch x (n, 3) (observe
        keeps what came before the batch)."""
        return np.concatenate([self._past, x[:k]])[-max(1, int(round(REVERSAL_PAST_S * odr_hz))):]

    def observe(self, x: np.ndarray, odr_hz: float) -> None:
        """The batch's remainder x (n, 3), kept for the next candidate's past (nothing where no candidate
        waits: reversal off, no arm's states, no wait)."""
        if self.reversal_s > 0.0 and self.arm is not None and self.lag_s > 0.0:
            self._past = self.past(x, len(x), odr_hz)

    def mask(self, t: np.ndarray):
        """What is still allowed of the last step the arm's states explained, decaying with STEP_RING_TAU_S."""
        amp, since = self.masked
        if amp == 0.0 or float(t[-1]) < since:
            return 0.0
        return amp * np.exp(-np.maximum(t - since, 0.0) / STEP_RING_TAU_S)

    def decide(self, t: np.ndarray, dev: np.ndarray | None, swing_accel: float, x: np.ndarray | None = None) -> int:
        """The waiting candidate: at once where the daemon's own commands were steady at it (`commands`),
        else against the arm's states, with this batch's accelerometer remainder
        `dev` (n,), or several views of it (k, n) whose peaks are each taken and the smallest weighed,
        and the remainder itself `x` (n, 3) for its reversal: the index of the sample it is decided at
        (an onset; `decided_t` its time), or -1 (still waiting, or the arm's own step)."""
        c = self.candidate
        if self.commands is not None and self.commands.steady(c.t):
            # the daemon drives the arm, and its commanded rates held: no step of its own
            self.candidate = None
            self.decided_t = c.t
            self.commanded += 1
            return min(int(np.searchsorted(t, c.t)), len(t) - 1)
        if x is not None and self.reversal_s > 0.0:
            at = self._reversal(t, x)
            if at >= 0:
                self.candidate = None
                self.decided_t = c.t
                self.reversals += 1
                return at
        if dev is not None:
            win = (t >= c.t) & (t <= c.t + PEAK_WINDOW_S)
            if win.any():
                views = np.atleast_2d(dev)[:, win].max(axis=1)
                c.views = views if c.views is None else np.maximum(c.views, views)
                c.peak = float(c.views.min())
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

    def _reversal(self, t: np.ndarray, x: np.ndarray) -> int:
        """The first sample within reversal_s of the candidate where the remainder x (n, 3), from its
        level before the candidate and along the direction of its largest value since (carried over
        batches), is below minus the larger of the candidate's threshold and REVERSAL_SWING_K times
        the swing before it along that direction: its index, or -1. (Along it, not in magnitude: a
        step along u plus a vibration whose component along u never exceeds its past swing stays above
        minus that swing; the vibration across u cannot turn the projection round.)"""
        c = self.candidate
        idx = np.flatnonzero((t >= c.t) & (t <= c.t + self.reversal_s))
        if len(idx) == 0:
            return -1
        xs = x[idx] if c.level is None else x[idx] - c.level
        if c.x_peak is not None:
            xs = np.concatenate([c.x_peak[None, :], xs])
        mag = np.sqrt(np.einsum("ij,ij->i", xs, xs))
        new_max = mag >= np.maximum.accumulate(mag)
        peak = np.maximum.accumulate(np.where(new_max, np.arange(len(xs)), 0))   # the running peak's row
        u = xs[peak] / np.maximum(mag[peak], 1e-12)[:, None]
        proj = np.einsum("ij,ij->i", xs, u)
        c.x_peak = xs[peak[-1]].copy()
        first = 1 if len(xs) > len(idx) else 0
        bar = np.full(len(xs), c.allow)
        if c.past is not None:
            bar = np.maximum(bar, REVERSAL_SWING_K * np.abs(c.past @ u.T).max(axis=0))
        hit = np.flatnonzero(proj[first:] < -bar[first:])
        return int(idx[hit[0]]) if len(hit) else -1


# A real arm's tool vibrates in a few narrow bands (its structural modes, the joints' harmonics, the servo's
# dither at rest); an impact is broadband and sudden. The accelerometer's condition is judged on what the
# remainder's own recent past does not predict PREDICT_HORIZON_S ahead (Predictor): the vibration is
# predicted away, an impact and an acceleration step the arm takes are not. Its taps span PREDICT_SPAN_S
# (a 40 Hz dither's period and more), fitted by least squares on the last PREDICT_TRAIN_S of armed data.
PREDICT_HORIZON_S = 0.001
PREDICT_TAPS = 16
PREDICT_SPAN_S = 0.008
PREDICT_TRAIN_S = 1.0
PREDICT_REFIT_S = 0.25
PREDICT_FIRST_S = 0.1         # the first fit, as soon as this much is learned (the trigger's warmup)
PREDICT_RIDGE = 1e-3          # the fit's ridge, relative to its data's mean square: coefficients never blow up


class Predictor:
    """The accelerometer remainder's PREDICT_HORIZON_S-ahead linear prediction from its own past, per
    axis: `error(x)` is what the prediction missed ((n, 3), the remainder itself until a fit exists).
    `learn` collects the armed remainder (contiguous runs; `gap` ends one) and refits every
    PREDICT_REFIT_S; a least-squares fit never makes the error's mean square on its data larger than
    the remainder's, so white noise gives coefficients near zero and the remainder back. A horizon of
    0: off, `error` is the remainder."""

    def __init__(self, horizon_s: float = PREDICT_HORIZON_S, odr_hz: float = 6667.0):
        self.horizon_s = horizon_s
        self.set_odr(odr_hz)

    @property
    def on(self) -> bool:
        return self.horizon_s > 0.0

    def set_odr(self, odr_hz: float) -> None:
        """Lags in samples at this rate; the fit and the history start afresh."""
        self.odr_hz = float(odr_hz)
        k = max(1, int(round(self.horizon_s * odr_hz)))
        stride = max(1, int(round(PREDICT_SPAN_S * odr_hz / PREDICT_TAPS)))
        self.lags = k + stride * np.arange(PREDICT_TAPS)
        self.reset()

    def reset(self) -> None:
        self.coef = np.zeros((len(self.lags), 3))
        self.fitted = False
        self._hist = np.zeros((int(self.lags[-1]), 3))
        self._runs: list[np.ndarray] = []       # contiguous runs of armed remainder, oldest first
        self._open = False                      # the newest run continues with the next batch
        self._new = 0                           # samples learned since the last fit

    def error(self, x: np.ndarray) -> np.ndarray:
        """The prediction error of the batch x (n, 3); the history carries over batches."""
        if not self.on:
            return x
        full = np.concatenate([self._hist, x])
        self._hist = full[-len(self._hist):]
        if not self.fitted:
            return x
        m, n = len(full) - len(x), len(x)
        pred = np.zeros_like(x)
        for j, lag in enumerate(self.lags):
            pred += self.coef[j] * full[m - lag:m - lag + n]
        return x - pred

    def gap(self) -> None:
        """The remainder stops being the arm's own (an episode, a wait, settling): the run ends."""
        self._open = False

    def learn(self, x: np.ndarray) -> bool:
        """Learn the batch x (n, 3); True when it gave the first fit (what was judged before on the
        remainder itself is then no measure of the error: NoiseFloor.restart)."""
        if not self.on:
            return False
        if self._open and self._runs:
            self._runs[-1] = np.concatenate([self._runs[-1], x])
        else:
            self._runs.append(np.array(x, dtype=float))
        self._open = True
        keep = int(PREDICT_TRAIN_S * self.odr_hz)
        total = sum(len(r) for r in self._runs)
        while total > keep and len(self._runs) > 1:
            total -= len(self._runs.pop(0))
        if total > keep:
            self._runs[0] = self._runs[0][total - keep:]
        self._new += len(x)
        first = not self.fitted
        if self._new >= (PREDICT_FIRST_S if first else PREDICT_REFIT_S) * self.odr_hz:
            return self._fit() and first
        return False

    def _fit(self) -> bool:
        span = int(self.lags[-1])
        runs = [r for r in self._runs if len(r) > span + 2 * len(self.lags)]
        if not runs:
            return False
        self._new = 0
        p = len(self.lags)
        for axis in range(3):
            xtx, xty, yy = np.zeros((p, p)), np.zeros(p), 0.0
            for r in runs:
                y = r[span:, axis]
                X = np.stack([r[span - lag:len(r) - lag, axis] for lag in self.lags], axis=1)
                xtx += X.T @ X
                xty += X.T @ y
                yy += float(y @ y)
            ridge = PREDICT_RIDGE * yy + 1e-12      # relative to the data's mean square, per row
            self.coef[:, axis] = np.linalg.solve(xtx + ridge * np.eye(p), xty)
        self.fitted = True
        return True
