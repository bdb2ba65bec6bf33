"""The estimators' input: IMU samples and proprioception aligned in time and frame, as one `Samples` record.

The contact pipeline (control.pipeline) finds the onset and hands each run of conditioned gyro
samples here; `Measurements.take` looks the robot's state up causally at each sample's instant
(ProprioTrack), turns the fingertip's rate into the object's with eta's schedule (EtaSchedule), pairs
each held TCP velocity with the rates from when it was measured (RateHistory), and says how much each
measurement is worth. Every estimator takes the record it returns, and uses what it needs of it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import relative_rotvec

PROPRIO_HISTORY = 256         # proprioception samples kept for causal lookup
TCP_TURNING_RAD_S = 0.01      # the gripper turns (its own rate from proprioception) above this
IMPACT_TAU_S = 0.015          # s, an arm moving at the onset: the grasp's take-up of its velocity (Measurements.take)
FRESH_MAX_AGE_S = 0.002       # a proprioception sample first seen later than this is no position measurement
DERIVED_V_FIRST_VAR = 1.0     # (m/s)^2 for the first sample when velocity must be derived
MAD_TO_SIGMA = 0.6745         # median |x| of a zero-mean normal, in its sigmas
WDOT_MAX_AGE_S = 0.05         # a reported TCP rate's last change is extrapolated at most this far
FINGERTIP_LAG_S = 0.003       # the silicone fingertip's viscoelastic lag, s: a rig's own, calibrated as eta is
PRE_ONSET_VAR = 1.0           # (m/s)^2: a TCP velocity measured before the onset, as no evidence
RATE_HISTORY_S = 0.2          # the object's rates kept for that pairing (proprioception older than this is stale)
# The TCP's acceleration (what the onset trigger subtracts from the accelerometer) is the slope of a
# least-squares line through the velocities of the last ACCEL_WINDOW_S, and of at least ACCEL_MIN_STATES
# states: a single difference of reported velocities is 0.7 m/s^2 of noise at 500 Hz and 1 mm/s, the
# slope over 20 ms a twelfth of that. It trails a jerk-limited plan by half the window (5 m/s^3 x 10 ms:
# 0.05 m/s^2).
ACCEL_WINDOW_S = 0.02
ACCEL_MIN_STATES = 4
SPECIFIC_FORCE_AT_REST = np.array([0.0, 0.0, 9.81])   # world (z up): an accelerometer at rest reads +g up


@dataclass(frozen=True)
class RigNoise:
    """The rig's measurement noise, SI: what the proprioception track and the pipeline's rotation axis
    assume whichever estimator runs. The config states it once, in `ekf`'s section (ContactKfParams)."""
    sigma_w: float = 0.01          # rad/s, per-sample object-rate noise (raw gyro noise x eta)
    sigma_p: float = 5e-5          # m, TCP position noise (encoder grade)
    sigma_v: float = 1e-3          # m/s, reported TCP velocity noise
    eta_rel_std: float = 0.05      # eta's relative uncertainty at its calibration

    @classmethod
    def of(cls, params) -> "RigNoise":
        """From anything that states these four (the `ekf` options)."""
        return cls(params.sigma_w, params.sigma_p, params.sigma_v, params.eta_rel_std)


class EtaSchedule:
    """Apparent transmission coefficient eta against grip force (N), linearly interpolated, clamped."""

    def __init__(self, table: list[tuple[float, float]] = ((30.0, 2.0),)):
        table = sorted((float(f), float(e)) for f, e in table)
        if not table or any(e <= 0 for _, e in table):
            raise ValueError("eta_table: expected [[force_N, eta], ...] with eta > 0")
        self.force = np.array([f for f, _ in table])
        self.eta = np.array([e for _, e in table])

    def __call__(self, force_n) -> np.ndarray:
        return np.interp(force_n, self.force, self.eta)

    def distance_n(self, force_n: float) -> float:
        """How far (N) a grip force lies from the nearest calibrated force."""
        return float(np.min(np.abs(self.force - force_n)))

    def prior(self, force_n: float, rel_std: float, rel_std_per_n: float) -> tuple[float, float]:
        """(mean, one-sigma) of k = eta_true / eta_scheduled at a grip force, from eta's relative
        uncertainty at a calibrated force and its growth per N away from one.

        Eta falls monotonically toward 1 as the grip force rises (the paper's calibration, Fig. 4c),
        so outside the calibrated forces the schedule, clamped at the nearest one, is known to be off
        in one direction: eta is larger below the lowest force and smaller above the highest. That
        part of the error is taken as half-normal, scale s = rel_std_per_n x distance, in the known
        direction: mean 1 +- s sqrt(2/pi), one-sigma rel_std + s sqrt(1 - 2/pi). Above the highest
        force the mean stays halfway above the bound eta >= 1. Between calibrated forces (interpolated)
        the error has no known sign: mean 1, one-sigma rel_std + s."""
        s = rel_std_per_n * self.distance_n(force_n)
        side = 1.0 if force_n < self.force[0] else -1.0 if force_n > self.force[-1] else 0.0
        if side == 0.0 or s == 0.0:
            return 1.0, rel_std + s
        mean = 1.0 + side * s * math.sqrt(2.0 / math.pi)
        if side < 0:
            mean = max(mean, 0.5 * (1.0 + 1.0 / self.eta[-1]))
        return mean, rel_std + s * math.sqrt(1.0 - 2.0 / math.pi)


HISTORY_SLACK = 4              # ProprioTrack's backing arrays hold this many windows of states
# ProprioTrack's fields and their initial values (a scalar, a row shape, or the identity). The
# history is a window of `size` states over backing arrays of HISTORY_SLACK * size: each field is
# a view of its backing array, moved one state on when the window is full, and the window is
# copied back to the start only once per (HISTORY_SLACK - 1) * size states (shifting 18 arrays on
# every state was a third of the estimator's time at rest).
HISTORY_FIELDS = {
    "t": np.inf,
    "p": (3,), "v": (3,),
    "tv": 0.0,                     # time the velocity belongs to
    "pv": (3,),                    # the TCP's position then
    "hv": 0.0,                     # half the span around tv that the velocity describes, s
    "var_v": 0.0,
    "a": 0.0,                      # |acceleration| estimate, m/s^2
    "acc": (3,),                   # the TCP's acceleration, world, m/s^2 (a fit over ACCEL_WINDOW_S)
    "acc_ok": False,               # acc[k] has been fitted
    # per state, what it says of the arm's own motion for the onset trigger (explained): the specific
    # force and the gripper's rate in the IMU frame, how far they may trail, |acceleration|
    "expl": (9,),
    "expl_ok": False,
    "alpha": 0.0,                  # |angular acceleration| estimate of the TCP, rad/s^2
    "tw": 0.0,                     # time the TCP rate belongs to
    "R": "eye",
    "w": (3,),
    "wdot": (3,),                  # angular acceleration of a reported TCP rate, rad/s^2 (0: derived)
    "force": np.nan,
}


def _backing(n: int, fill) -> np.ndarray:
    """A backing array of n rows for a field: a scalar fill (float or bool), a row shape, or "eye" (3x3)."""
    if fill == "eye":
        return np.tile(np.eye(3), (n, 1, 1))
    if isinstance(fill, tuple):
        return np.zeros((n, *fill))
    if isinstance(fill, bool):
        return np.full(n, fill, dtype=bool)
    return np.full(n, fill)


class ProprioTrack:
    """Recent TCP states for causal lookup: an IMU sample at time t sees only states stamped at or before t.

    Velocity is the robot's reported TCP velocity when given; otherwise the
    backward difference of the last two positions (which belongs to the middle
    of their interval). Each lookup carries a velocity variance: the source's
    noise plus the staleness of holding it (|a| * age)^2, with |a| from the
    last two velocities.
    """

    def __init__(self, size: int = PROPRIO_HISTORY, sigma_p: float = 5e-5, sigma_v: float = 1e-3):
        self.size = size
        self.sigma_p = sigma_p
        self.sigma_v = sigma_v
        self._backing = {name: _backing(HISTORY_SLACK * size, fill) for name, fill in HISTORY_FIELDS.items()}
        self._start = 0
        self._view()
        self.imu_mount = np.eye(3)         # R_tcp_imu
        self.n = 0
        self._rate = np.nan
        self._rate_n = 0
        self._noise = 0.0
        self._noise_at = 0            # `added` when the noise was last measured
        self.added = 0                # samples added so far (the history itself is a window)

    def add(self, t: float, p: np.ndarray, v: np.ndarray | None, R: np.ndarray, w: np.ndarray | None,
            force: float = np.nan) -> None:
        """One proprioception sample; v and w (the TCP's rate, world) may be None: derived then."""
        n = self.n
        if n and t <= self.t[n - 1]:
            return   # repeated or out of order: keep time strictly increasing
        if v is None:
            if n:
                dt = t - self.t[n - 1]
                v = (p - self.p[n - 1]) / dt
                tv, var_v = t - dt / 2, 2 * self.sigma_p_effective() ** 2 / dt ** 2
                pv, hv = 0.5 * (p + self.p[n - 1]), dt / 2      # the mean velocity over the interval
            else:
                v, tv, var_v, pv, hv = np.zeros(3), t, DERIVED_V_FIRST_VAR, p, 0.0
        else:
            # at its stamp; it stands for the half periods either side (the rate's mean over them)
            tv, var_v, pv, hv = t, self.sigma_v ** 2, p, (t - self.t[n - 1]) / 2 if n else 0.0
        wdot = np.zeros(3)
        if w is None:
            # Backward difference of orientations: it belongs to the middle of the interval.
            if n:
                dt = t - self.t[n - 1]
                w, tw = np.array(relative_rotvec(R.tolist(), self.R[n - 1].tolist())) / dt, t - dt / 2
            else:
                w, tw = np.zeros(3), t
        else:
            tw = t
            if n and self.tw[n - 1] == self.t[n - 1]:
                # two reported rates: extrapolate the rate between samples, not hold it
                wdot = (w - self.w[n - 1]) / (t - self.t[n - 1])
        a = math.dist(v, self.v[n - 1]) / max(tv - self.tv[n - 1], 1e-6) if n else 0.0
        alpha = math.dist(w, self.w[n - 1]) / max(tw - self.tw[n - 1], 1e-6) if n else 0.0
        if n == self.size:
            self._slide()
            n -= 1
        self.acc_ok[n] = self.expl_ok[n] = False       # fitted when first asked for (explained)
        self.t[n], self.p[n], self.v[n], self.tv[n], self.var_v[n] = t, p, v, tv, var_v
        self.pv[n], self.hv[n] = pv, hv
        self.a[n], self.alpha[n], self.tw[n], self.R[n], self.w[n], self.force[n] = a, alpha, tw, R, w, force
        self.wdot[n] = wdot
        self.n = n + 1
        self.added += 1

    def _view(self) -> None:
        for name, arr in self._backing.items():
            setattr(self, name, arr[self._start:self._start + self.size])

    def _slide(self) -> None:
        """Drop the oldest state: the window moves on by one; at the end of the backing arrays, the
        newest size - 1 states go back to their start."""
        if self._start + self.size < len(self._backing["t"]):
            self._start += 1
        else:
            keep = self.size - 1
            for arr in self._backing.values():
                arr[:keep] = arr[self._start + 1:self._start + self.size]
            self._start = 0
        self._view()

    def _fit_accel(self, k: int) -> np.ndarray:
        """The TCP's acceleration as of state k: the slope of the least-squares line through the
        velocities of the last ACCEL_WINDOW_S up to it (at least ACCEL_MIN_STATES)."""
        if k == 0:
            return np.zeros(3)
        tv = self.tv[:k + 1]
        k0 = int(np.searchsorted(tv, tv[k] - ACCEL_WINDOW_S, side="left"))
        k0 = max(min(k0, k - ACCEL_MIN_STATES + 1), 0)
        dt = tv[k0:] - float(np.add.reduce(tv[k0:])) / (k + 1 - k0)
        den = float(dt @ dt)
        if den <= 0.0:
            return np.zeros(3)
        return (dt @ self.v[k0:k + 1]) / den

    def _fitted(self, k: int) -> np.ndarray:
        if not self.acc_ok[k]:
            self.acc[k] = self._fit_accel(k)
            self.acc_ok[k] = True
        return self.acc[k]

    def explained(self, ts: np.ndarray) -> np.ndarray | None:
        """What the arm's own motion accounts for at the IMU samples stamped ts (n,), from the state
        each holds (causal; samples before the first state take the first state's): (n, 9) rows of
        the specific force (gravity and the TCP's acceleration) and the gripper's rate, both in the
        IMU's frame (`imu_mount`: R_tcp_imu), half the change of the acceleration and of the rate
        over the ACCEL_WINDOW_S before the state (m/s^2, rad/s: how far a fit over that window may
        trail the arm), and |acceleration|. None before any state. Each state's row is made once."""
        if self.n == 0:
            return None
        j = np.maximum(np.searchsorted(self.t[:self.n], ts, side="right") - 1, 0)
        if not self.expl_ok[j[-1]] or not self.expl_ok[j[0]]:
            for k in range(int(j[0]), int(j[-1]) + 1):
                if not self.expl_ok[k]:
                    self._explain(k)
        return self.expl[j]

    def _explain(self, k: int) -> None:
        before = max(int(np.searchsorted(self.tv[:k + 1], self.tv[k] - ACCEL_WINDOW_S, side="right")) - 1, 0)
        acc = self._fitted(k)
        da = acc - self._fitted(before)
        dw = self.w[k] - self.w[before]
        M = self.R[k] @ self.imu_mount                      # world <- IMU
        row = self.expl[k]
        row[0:3] = (acc + SPECIFIC_FORCE_AT_REST) @ M
        row[3:6] = self.w[k] @ M
        row[6] = 0.5 * math.sqrt(float(da @ da))
        row[7] = 0.5 * math.sqrt(float(dw @ dw))
        row[8] = math.sqrt(float(acc @ acc))
        self.expl_ok[k] = True

    def sigma_p_effective(self) -> float:
        """The TCP position's noise, m: the configured sigma_p, or more where the positions show it.

        The configured value is a floor. A rig's actual noise can be ten times more (the paper's
        0.5 mm against an encoder's 0.05 mm), and a filter that trusts positions and the
        velocities derived from them ten times too much drifts. So the noise is measured from the
        positions' second differences, which cancel a steady motion: for white noise each has a
        variance of 6 sigma^2. Their median is robust to the starts and stops. Re-measured every
        16 samples over the history."""
        n = self.n
        if n < 8:
            return self.sigma_p
        if self._noise_at == 0 or self.added - self._noise_at >= 16:
            p = self.p[:n]
            d2 = p[2:] - 2.0 * p[1:-1] + p[:-2]
            self._noise = float(np.median(np.abs(d2))) / (MAD_TO_SIGMA * math.sqrt(6.0))
            self._noise_at = self.added
        return max(self.sigma_p, self._noise)

    def rate_hz(self) -> float:
        """Median proprioception rate, Hz (recomputed every 16 samples)."""
        if self.n < 3:
            return np.nan
        if self._rate_n == 0 or self.n - self._rate_n >= 16 or self.n < self._rate_n:
            self._rate = float(1.0 / np.median(np.diff(self.t[:self.n])))
            self._rate_n = self.n
        return self._rate

    def lookup(self, ts: np.ndarray, with_stamp: bool = False):
        """(p, v, R, w, var_v, var_w, force, ok) at times ts, extrapolated from the newest state at or before each.

        var_w is the staleness variance of the TCP's own rate w, (rad/s)^2. With `with_stamp`
        the stamp of the state each time used is appended.
        """
        j = np.searchsorted(self.t[:self.n], ts, side="right") - 1
        ok = j >= 0
        j = np.maximum(j, 0)
        age = ts - self.t[j]
        p = self.p[j] + self.v[j] * age[:, None]
        var_v = self.var_v[j] + (self.a[j] * (ts - self.tv[j])) ** 2
        var_w = (self.alpha[j] * (ts - self.tw[j])) ** 2
        # a reported TCP rate is extrapolated with its last change (a turning gripper's rate ramps;
        # held for up to a proprioception period it would enter the object rate times (eta - 1)), but
        # not without bound: when proprioception stalls, the rate is held after WDOT_MAX_AGE_S
        w = self.w[j] + self.wdot[j] * np.minimum(ts - self.tw[j], WDOT_MAX_AGE_S)[:, None]
        if with_stamp:
            return p, self.v[j], self.R[j], w, var_v, var_w, self.force[j], ok, self.t[j]
        return p, self.v[j], self.R[j], w, var_v, var_w, self.force[j], ok

    def rate_at(self, ts: np.ndarray) -> np.ndarray:
        """The TCP's own rate (world, rad/s) at times ts (n,): interpolated between the times the
        rates belong to (a derived rate to the middle of its interval), past the newest one
        extrapolated with the last change for at most WDOT_MAX_AGE_S."""
        n = self.n
        tw, w = self.tw[:n], self.w[:n]
        if n < 2:
            return np.tile(w[-1] if n else np.zeros(3), (len(ts), 1))
        out = np.column_stack([np.interp(ts, tw, w[:, a]) for a in range(3)])
        late = ts > tw[-1]
        if late.any():
            slope = (w[-1] - w[-2]) / max(tw[-1] - tw[-2], 1e-6)
            out[late] = w[-1] + np.minimum(ts[late] - tw[-1], WDOT_MAX_AGE_S)[:, None] * slope
        return out

    def velocity_at(self, ts: np.ndarray):
        """What the velocity held at times ts belongs to: (the TCP's position then (n, 3), the time
        tv it belongs to and the half span h around it that it describes (n,) each: a derived
        velocity the interval between its two positions, a reported one the half periods either
        side of its stamp; its noise variance, (m/s)^2, without staleness)."""
        j = np.maximum(np.searchsorted(self.t[:self.n], ts, side="right") - 1, 0)
        return self.pv[j], self.tv[j], self.hv[j], self.var_v[j]


class RateHistory:
    """The episode's fingertip rates (the IMU's, in the world, rad/s) against time, for the mean over
    a past span: what a held TCP velocity is paired with (Measurements.take). Kept for
    RATE_HISTORY_S; cumulative sums make each mean two lookups."""

    def __init__(self):
        self.start(np.nan)

    def start(self, t0: float) -> None:
        """A new episode: no rates before t0 (the onset; the fingertip then turned with the gripper)."""
        self.t0 = t0
        self.t = np.zeros(0)
        self.cw = np.zeros((1, 3))          # cw[i]: the sum of the first i rates

    def add(self, t: np.ndarray, w: np.ndarray) -> None:
        if len(self.t) and self.t[-1] - self.t[0] > 2 * RATE_HISTORY_S:
            keep = int(np.searchsorted(self.t, self.t[-1] - RATE_HISTORY_S))
            self.t = self.t[keep:]
            self.cw = self.cw[keep:] - self.cw[keep]
        self.t = np.concatenate([self.t, t])
        self.cw = np.concatenate([self.cw, self.cw[-1] + np.cumsum(w, axis=0)])

    def mean(self, t0: np.ndarray, t1: np.ndarray, before: np.ndarray, dt_sample: float):
        """(the mean rate over each span [t0, t1] (n, 3), the samples it averages (n,)). The part of a
        span before the episode counts as `before` (n, 3), one sample per dt_sample."""
        i0 = np.searchsorted(self.t, t0, side="left")
        i1 = np.searchsorted(self.t, t1, side="right")
        got = np.maximum(i1 - i0, 0)
        missing = np.clip(np.round((np.minimum(t1, self.t0) - t0) / dt_sample), 0, None)
        total = self.cw[np.maximum(i1, i0)] - self.cw[i0] + missing[:, None] * before
        count = got + missing
        empty = count == 0
        if empty.any():          # a span in a gap (clipped samples left out): the nearest rate, else the one before
            if len(self.t):
                j = np.clip(i0[empty], 0, len(self.t) - 1)
                total[empty] = self.cw[j + 1] - self.cw[j]
            else:
                total[empty] = before[empty]
            count = np.where(empty, 1, count)
        return total / count[:, None], count


@dataclass(frozen=True)
class Samples:
    """A run of IMU samples as every estimator takes them: world frame, SI, one row per sample, each
    stamped at the instant its low-pass filtered gyro describes. An estimator uses what it needs.

    The rows an estimator sees are causal: every value is from data stamped at or before `t`."""
    t: np.ndarray                    # (n,) s, the sample's instant
    dt: np.ndarray                   # (n,) s since the previous sample (the episode's first: at least 1 us)
    w: np.ndarray                    # (n, 3) rad/s, the object's rate at the scheduled eta
    p: np.ndarray                    # (n, 3) m, the TCP's position then (extrapolated from the newest state)
    v: np.ndarray                    # (n, 3) m/s, the TCP velocity the newest state holds
    var_v: np.ndarray | None = None  # (n,) (m/s)^2, v's noise and staleness (None: the estimator's own)
    var_w: np.ndarray | None = None  # (n,) (rad/s)^2, the rate's extra variance from a stale gripper rate
    w_tcp: np.ndarray | None = None  # (n, 3) rad/s, the gripper's own rate; zeros while it counts as still
    fresh: np.ndarray | None = None  # (n,) bool: the first sample that sees a new TCP position (None: none known)
    # What the TCP positions pair with as evidence of a rigid pivot: the positions, and the rates
    # read `fingertip_lag_s` after each (the fingertip's twist reaches the IMU that late)
    w_pos: np.ndarray | None = None
    p_pos: np.ndarray | None = None
    w_tcp_pos: np.ndarray | None = None
    # What the held velocity v pairs with, from when it was measured: the object's rate (a mean over
    # n_avg samples), the gripper's rate and the TCP's position (n_avg None: v as of each sample)
    w_v: np.ndarray | None = None
    w_tcp_v: np.ndarray | None = None
    p_v: np.ndarray | None = None
    n_avg: np.ndarray | None = None
    eta: np.ndarray | None = None    # (n,) the scheduled eta at each sample's grip force
    force: np.ndarray | None = None  # (n,) N, the grip force (measured, else the configured one)
    R: np.ndarray | None = None      # (n, 3, 3) the TCP's orientation, world <- TCP
    accel: np.ndarray | None = None  # (n, 3) m/s^2, the IMU's specific force, IMU frame
    turning: bool = False            # the gripper turns in this run (w_tcp and its kin are its rate)

    @classmethod
    def of(cls, dt, w, p, v, **rest) -> "Samples":
        """A record from the four every estimator takes (rows of (n,) and (n, 3) arrays); the rest
        as given, the position and pairing rows defaulting to those of each sample."""
        w_tcp = rest.pop("w_tcp", None)
        turning = rest.pop("turning", w_tcp is not None)
        w_tcp = np.zeros((len(dt), 3)) if w_tcp is None else w_tcp
        t = rest.pop("t", np.cumsum(dt))
        return cls(t=t, dt=dt, w=w, p=p, v=v, w_tcp=w_tcp, turning=turning,
                   **{"w_pos": w, "p_pos": p, "w_tcp_pos": w_tcp, "w_v": w, "w_tcp_v": w_tcp, "p_v": p, **rest})

    def __len__(self) -> int:
        return len(self.dt)

    def __getitem__(self, rows) -> "Samples":
        """The rows `rows` (a slice or a mask) of every array."""
        return dataclasses.replace(self, **{f.name: getattr(self, f.name)[rows] for f in _ROWS
                                            if getattr(self, f.name) is not None})


_ROWS = tuple(f for f in dataclasses.fields(Samples) if f.name != "turning")


class Measurements:
    """The alignment half of the pipeline: proprioception, eta and the fingertip's lag turned into one
    `Samples` record per run of conditioned IMU samples. It keeps what pairs measurements across
    batches: the episode's rates (RateHistory), the last proprioception stamp seen, the onset."""

    def __init__(self, cond, eta: EtaSchedule, proprio: ProprioTrack, grip_force_n: float, fingertip_lag_s: float):
        self.cond = cond                       # control.conditioning.GyroConditioner: delay and frames
        self.eta = eta
        self.proprio = proprio
        self.grip_force_n = grip_force_n       # N, used where no grip force is measured
        self.lag_s = fingertip_lag_s
        self.rates = RateHistory()
        self.onset_t = np.nan
        self.v_onset = 0.0                     # m/s, the TCP's speed at the onset beyond its noise
        self.grip_force_now = np.nan           # N, at the newest sample taken (a measurement or not)
        self._stamp_prev = np.nan

    def begin(self, onset_t: float, v_onset: float, rates_from_t: float) -> None:
        """A contact episode from `onset_t`, the TCP then moving at `v_onset` (m/s beyond its noise:
        0 from rest); the object's rates count from `rates_from_t` (the onset less the low-pass delay)."""
        self.onset_t = onset_t
        self.v_onset = v_onset
        self._stamp_prev = np.nan
        self.rates.start(rates_from_t)

    def take(self, ts, w_f, ok, accel, timing: tuple[float, float]) -> Samples:
        """The record for samples stamped ts (n,) with filtered, bias-free gyro w_f (n, 3, IMU frame) and
        specific force accel (n, 3); ok (n,) False for samples that are no measurement (clipped at
        full scale), which are left out. timing: (the IMU's sample period, the last sample time the
        estimator has taken, or None)."""
        dt_sample, t_prev = timing
        # The causal low-pass delays the gyro by its group delay; take proprioception at the same
        # (earlier) instant so that w and v describe the same moment. Still causal.
        delay = self.cond.group_delay_samples * dt_sample
        p, v, R, w_tcp, var_v, var_wt, force, found, stamp = self.proprio.lookup(ts - delay, with_stamp=True)
        force = np.where(np.isnan(force), self.grip_force_n, force)
        self.grip_force_now = float(force[-1])
        eta = self.eta(force)
        w_obj = self.cond.object_rate_world(w_f, R, w_tcp, eta[:, None])
        p_pos, w_pos, w_tcp_pos, fresh = self._positions(ts - delay, w_obj, w_tcp, found, (p, stamp))
        var_w = (eta - 1.0) ** 2 * var_wt
        ok = found & ok
        self.rates.add((ts - delay)[ok], self.cond.object_rate_world(w_f[ok], R[ok], np.zeros(3), 1.0))
        p_v, w_v, w_tcp_v, var_v, n_avg = self._paired(ts - delay, eta, dt_sample)
        # While the gripper itself turns the estimator needs its rate: eta's error scales only the
        # object's rotation relative to the gripper. Otherwise every rotation is the object's.
        turning = float(np.max(np.einsum("ij,ij->i", w_tcp, w_tcp))) > TCP_TURNING_RAD_S ** 2
        if not turning:
            w_tcp, w_tcp_pos, w_tcp_v = np.zeros_like(w_tcp), np.zeros_like(w_tcp_pos), np.zeros_like(w_tcp_v)
        rows = Samples(t=ts, dt=ts, w=w_obj, p=p, v=v, var_v=var_v, var_w=var_w, w_tcp=w_tcp, fresh=fresh,
                       w_pos=w_pos, p_pos=p_pos, w_tcp_pos=w_tcp_pos, w_v=w_v, w_tcp_v=w_tcp_v, p_v=p_v, n_avg=n_avg,
                       eta=eta, force=force, R=R, accel=accel, turning=turning)
        if not ok.all():
            rows = rows[ok]
        prev = t_prev if t_prev is not None else np.nan
        return dataclasses.replace(rows, dt=np.maximum(np.diff(rows.t, prepend=prev), 1e-6))

    def _positions(self, ts, w_obj, w_tcp, found, now):
        """(p, w, w_tcp, fresh) for the position evidence. The positions integrate the object's rotation
        up to each TCP position; the fingertip's twist reaches the IMU `lag` late, so the twist read
        now is the object's relative rotation at now - lag: each position pairs with the twist read
        lag after it, and with the gripper's own rotation up to its own time. Unpaired, the angle
        trails the displacement by rate x lag, and the lever arm reads long by lag / t (millimetres
        at 100 ms on a 12 cm arc: docs/estimation.md). A proprioception sample is a position measurement
        at the first IMU sample that sees it (extrapolated by less than one IMU period; later ones
        are not taken)."""
        lag = self.lag_s
        p, stamp = now
        if lag > 0:
            p, _, _, w_tcp_pos, _, _, _, found, stamp = self.proprio.lookup(ts - lag, with_stamp=True)
            w_pos = w_obj - w_tcp + w_tcp_pos
        else:
            w_tcp_pos, w_pos = w_tcp, w_obj
        new = np.diff(stamp, prepend=self._stamp_prev) != 0
        fresh = new & ((ts - lag - stamp) <= FRESH_MAX_AGE_S) & found
        if self.v_onset > 0.0:
            # an arm moving at the onset: its displacement while the grasp takes up the motion is not
            # the pivot's (IMPACT_TAU_S); positions count from three time constants on (the offset the
            # take-up leaves is the regression's intercept)
            fresh &= stamp >= self.onset_t + 3.0 * IMPACT_TAU_S
        self._stamp_prev = float(stamp[-1])
        return p, w_pos, w_tcp_pos, fresh

    def _paired(self, ts, eta, dt_sample):
        """What each held velocity pairs with: (p_v, w_v, w_tcp_v, var_v, n_avg).

        A held TCP velocity was measured at its stamp (a derived one over the interval to it): it pairs
        with the object's rate and the TCP's position then, not with those of each sample that holds
        it. At 65 Hz that is up to a period of change: from a start at rest the held velocity still
        reads zero while the object already turns, and the lever arm reads short. The history holds
        the IMU's own rate in the world; the object's rate is made from its mean with the gripper's
        rate of the same moment (a gripper rate extrapolated past a change would enter it (eta - 1)
        times). The fingertip's twist, which the IMU reads, lags the object's by the silicone's
        viscoelastic time constant (the paper's "phase lag", Sec. III-B, which its eta leaves out): the
        twist read at tv + lag is the object's at tv. The gripper's own rotation reaches the IMU at once."""
        lag = self.lag_s
        p_v, tv, hv, var_v = self.proprio.velocity_at(ts)
        w_tcp_v = self.proprio.rate_at(tv)
        w_tcp_lag = self.proprio.rate_at(tv + lag) if lag > 0 else w_tcp_v
        # the span the velocity stands for, as much of it as has been measured by each sample
        h = np.clip(ts - tv - lag, 0.0, hv)
        w_imu_v, n_avg = self.rates.mean(tv + lag - h, tv + lag + h, w_tcp_lag, dt_sample)
        w_v = w_tcp_v + eta[:, None] * (w_imu_v - w_tcp_lag)
        # A velocity measured before the touch is no evidence of the pivot: an arm already moving into
        # an edge moved the object with it (only a start from rest agrees with the model).
        var_v = np.where(tv < self.rates.t0, PRE_ONSET_VAR, var_v)
        # An arm already moving at the onset (an ongoing motion into an edge) first pushes through the
        # compliant grasp: the object takes up its rotation over the fingertip's and the grasp's give,
        # and until then the TCP's velocity is not the pivot's (its lever arm reads several times too
        # long over the first 10 ms: docs/estimation.md). That part of the velocity is distrusted as
        # it decays, IMPACT_TAU_S (nothing from rest).
        if self.v_onset > 0.0:
            v_push = self.v_onset * np.exp(-np.maximum(tv - self.rates.t0, 0.0) / IMPACT_TAU_S)
            var_v = var_v + v_push * v_push
        return p_v, w_v, w_tcp_v, var_v, n_avg
