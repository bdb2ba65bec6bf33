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

from tecdard.control.proprio import ProprioTrack

TCP_TURNING_RAD_S = 0.01      # the gripper turns (its own rate from proprioception) above this
IMPACT_TAU_S = 0.015          # s, an arm moving at the onset: the grasp's take-up of its velocity (Measurements.take)
FRESH_MAX_AGE_S = 0.002       # a proprioception sample first seen later than this is no position measurement
FINGERTIP_LAG_S = 0.003       # the silicone fingertip's viscoelastic lag, s: a rig's own, calibrated as eta is
PRE_ONSET_VAR = 1.0           # (m/s)^2: a TCP velocity measured before the onset, as no evidence
RATE_HISTORY_S = 0.2          # the object's rates kept for that pairing (proprioception older than this is stale)


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
        self.grip_force_n = np.array([f for f, _ in table])
        self.eta = np.array([e for _, e in table])

    def __call__(self, force_n) -> np.ndarray:
        return np.interp(force_n, self.grip_force_n, self.eta)

    def distance_n(self, force_n: float) -> float:
        """How far (N) a grip force lies from the nearest calibrated force."""
        return float(np.min(np.abs(self.grip_force_n - force_n)))

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
        side = 1.0 if force_n < self.grip_force_n[0] else -1.0 if force_n > self.grip_force_n[-1] else 0.0
        if side == 0.0 or s == 0.0:
            return 1.0, rel_std + s
        mean = 1.0 + side * s * math.sqrt(2.0 / math.pi)
        if side < 0:
            mean = max(mean, 0.5 * (1.0 + 1.0 / self.eta[-1]))
        return mean, rel_std + s * math.sqrt(1.0 - 2.0 / math.pi)



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
        total = self.cw.take(np.maximum(i1, i0), axis=0) - self.cw.take(i0, axis=0) + missing[:, None] * before
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
    grip_force_n: np.ndarray | None = None  # (n,) N, the grip force (measured, else the configured one)
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
        at = self.proprio.lookup(ts - delay)
        p, v, R, w_tcp, var_v, var_wt, found, stamp = at.p, at.v, at.R, at.w, at.var_v, at.var_w, at.ok, at.stamp
        grip_force_n = np.where(np.isnan(at.grip_force_n), self.grip_force_n, at.grip_force_n)
        self.grip_force_now = float(grip_force_n[-1])
        eta = self.eta(grip_force_n)
        # the fingertip's rate in the world once: the object's is made from it, and the rate history
        # keeps it as it is (object_rate_world with no gripper rate and eta 1, row by row the same)
        w_imu_world = self.cond.imu_rate_world(w_f, R)
        w_obj = w_tcp + eta[:, None] * (w_imu_world - w_tcp)
        p_pos, w_pos, w_tcp_pos, fresh = self._positions(ts - delay, w_obj, w_tcp, found, (p, stamp))
        var_w = (eta - 1.0) ** 2 * var_wt
        ok = found & ok
        self.rates.add((ts - delay)[ok], w_imu_world[ok])
        p_v, w_v, w_tcp_v, var_v, n_avg = self._paired(ts - delay, eta, dt_sample)
        # While the gripper itself turns the estimator needs its rate: eta's error scales only the
        # object's rotation relative to the gripper. Otherwise every rotation is the object's.
        turning = float(np.max(np.einsum("ij,ij->i", w_tcp, w_tcp))) > TCP_TURNING_RAD_S ** 2
        if not turning:
            w_tcp, w_tcp_pos, w_tcp_v = np.zeros_like(w_tcp), np.zeros_like(w_tcp_pos), np.zeros_like(w_tcp_v)
        rows = Samples(t=ts, dt=ts, w=w_obj, p=p, v=v, var_v=var_v, var_w=var_w, w_tcp=w_tcp, fresh=fresh,
                       w_pos=w_pos, p_pos=p_pos, w_tcp_pos=w_tcp_pos, w_v=w_v, w_tcp_v=w_tcp_v, p_v=p_v, n_avg=n_avg,
                       eta=eta, grip_force_n=grip_force_n, R=R, accel=accel, turning=turning)
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
            at = self.proprio.lookup(ts - lag)
            p, w_tcp_pos, found, stamp = at.p, at.w, at.ok, at.stamp
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
