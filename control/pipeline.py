"""Contact pipeline: onset trigger -> gyro conditioning -> contact estimator, on IMU batches, causally.

Used by the daemon's estimator thread and by `tecdard localize` alike.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tecdard.control import estimators
from tecdard.control.estimators import Snapshot
from tecdard.control.baselines import BaselineParams
from tecdard.control.conditioning import GyroConditioner
from tecdard.control.ekf import UNOBSERVED_STD_M, ContactKfParams, PaperEkfParams
from tecdard.control.geometry import Plane, relative_rotvec
from tecdard.control.kernels import plane_rotation, rate_moments, rotation_axes
from tecdard.control.onset import OnsetDetector
from tecdard.drivers.lsm6dsr import Scaling

PROPRIO_HISTORY = 256         # proprioception samples kept for causal lookup
CONVERGED_STD_M = 0.005       # converged when the in-plane one-sigma (x the root NIS ratio above 1) is below this
MIN_AXIS_RATE_RAD_S = 1e-3
SECOND_AXIS_RATIO = 0.05      # a rotation about a 2nd axis this strong (by variance) makes 3D observable
TCP_TURNING_RAD_S = 0.01      # the gripper turns (its own rate from proprioception) above this
IMPACT_TAU_S = 0.015           # s, an arm moving at the onset: the grasp's take-up of its velocity (process_all)
FRESH_MAX_AGE_S = 0.002      # a proprioception sample first seen later than this is no position measurement
DERIVED_V_FIRST_VAR = 1.0     # (m/s)^2 for the first sample when velocity must be derived
MAD_TO_SIGMA = 0.6745         # median |x| of a zero-mean normal, in its sigmas
WDOT_MAX_AGE_S = 0.05         # a reported TCP rate's last change is extrapolated at most this far
FINGERTIP_LAG_S = 0.003       # the silicone fingertip's viscoelastic lag, s: a rig's own, calibrated as eta is
PRE_ONSET_VAR = 1.0           # (m/s)^2: a TCP velocity measured before the onset, as no evidence
RATE_HISTORY_S = 0.2          # the object's rates kept for that pairing (proprioception older than this is stale)
# The LSM6DSR's clipping points at its default full scales (4000 dps, 16 g: 80.06 rad/s, 156.8 m/s^2),
# until a source says which scales it runs.
DEFAULT_SATURATION = Scaling().saturation
SATURATED_BATCH_FRACTION = 0.5    # a batch this clipped counts toward a clipped stream (a stuck or overloaded chip)


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
        self.t = np.full(size, np.inf)
        self.p = np.zeros((size, 3))
        self.v = np.zeros((size, 3))
        self.tv = np.zeros(size)           # time the velocity belongs to
        self.pv = np.zeros((size, 3))      # the TCP's position then
        self.hv = np.zeros(size)           # half the span around tv that the velocity describes, s
        self.var_v = np.zeros(size)
        self.a = np.zeros(size)            # |acceleration| estimate, m/s^2
        self.alpha = np.zeros(size)        # |angular acceleration| estimate of the TCP, rad/s^2
        self.tw = np.zeros(size)           # time the TCP rate belongs to
        self.R = np.tile(np.eye(3), (size, 1, 1))
        self.w = np.zeros((size, 3))
        self.wdot = np.zeros((size, 3))    # angular acceleration of a reported TCP rate, rad/s^2 (0: derived)
        self.force = np.full(size, np.nan)
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
            for arr in (self.t, self.p, self.v, self.tv, self.pv, self.hv, self.var_v, self.a, self.alpha, self.tw,
                        self.R, self.w, self.wdot, self.force):
                arr[:-1] = arr[1:]
            n -= 1
        self.t[n], self.p[n], self.v[n], self.tv[n], self.var_v[n] = t, p, v, tv, var_v
        self.pv[n], self.hv[n] = pv, hv
        self.a[n], self.alpha[n], self.tw[n], self.R[n], self.w[n], self.force[n] = a, alpha, tw, R, w, force
        self.wdot[n] = wdot
        self.n = n + 1
        self.added += 1

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
    a past span: what a held TCP velocity is paired with (ContactPipeline.process_all). Kept for
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


@dataclass
class ContactEstimate:
    t: float                  # s, time of the last IMU sample used
    onset_t: float            # s
    p: np.ndarray             # contact / hinge point, world, m
    std: np.ndarray           # one-sigma per world axis, m
    cov: np.ndarray           # 3 x 3 covariance, world, m^2
    axis: np.ndarray | None   # rotation axis estimate, world unit (None until excited)
    converged: bool
    nis: float
    steps: int
    method: str = "ekf"
    in_plane_std: float = float("inf")   # statistical one-sigma in the plane of rotation, m
    angle_rad: float = 0.0               # rotation of the object since onset, integrated from the gyro
    nis_ratio: float | None = None       # smoothed innovation NIS / its expectation (None: no innovations)
    onset_p_tcp: np.ndarray | None = None    # the TCP at the onset sample, world, m
    saturated: int = 0                   # samples of this episode clipped at full scale (not used by the filter)
    extra: dict = field(default_factory=dict)

    def to_json(self, method: str | None = None) -> dict:
        return {"t": self.t, "onset_t": self.onset_t, "p": self.p.tolist(), "std": self.std.tolist(),
                "converged": self.converged, "method": method or self.method,
                "axis": None if self.axis is None else self.axis.tolist(), "angle_deg": math.degrees(self.angle_rad),
                "nis_ratio": self.nis_ratio, "saturated_samples": self.saturated}


@dataclass(frozen=True)
class EstimatorDirective:
    """What the control thread wants of the estimator, as state: the control thread replaces it
    (a LatestValue), the estimator thread applies whatever differs from what it applied last. A
    value cannot be lost the way a queued message can; a new episode number releases the contact
    episode (older onsets no longer count), and two episodes begun between two looks of the
    estimator are one release."""
    episode: int = 0                   # changes: end the contact episode (release)
    armed: bool = True                 # the onset trigger is armed
    arc_following: bool = False        # the arm follows an arc about the estimate (ContactKF.radial_var)
    bias_held: bool = False            # the tool touches outside an episode: no gyro bias tracking
    begin_t: float | None = None       # with a new episode: start it at this time without the trigger


@dataclass
class PipelineParams:
    method: str = "ekf"
    plane_normal: np.ndarray | None = None     # world; None: 3D
    output_period_s: float = 0.005             # estimates are emitted at most this often
    eta_table: list = field(default_factory=lambda: [(30.0, 2.0)])
    grip_force_n: float = 30.0                 # used when no grip force is measured
    eta_rel_std_per_n: float = 0.02            # eta's relative uncertainty grows this much per N off calibration
    arc_radial_sigma: float = 0.005            # m/s, distrust of the velocity along the lever arm while arc following
    fingertip_lag_s: float = FINGERTIP_LAG_S   # s, the fingertip twist's lag behind the object (see process_all)
    ekf: ContactKfParams = field(default_factory=ContactKfParams)
    paper_ekf: PaperEkfParams = field(default_factory=PaperEkfParams)
    baseline: BaselineParams = field(default_factory=BaselineParams)


def make_estimator(params: PipelineParams, plane: Plane | None):
    """The estimator named by params.method (control/estimators/)."""
    return estimators.build(params.method, params, plane)


class ContactPipeline:
    """Event-driven estimation: idle (bias and rest tracking) until the trigger fires, then the estimator.

    `process(batch)` takes an (n, 7) array of t, gyro xyz (rad/s), accel xyz
    (m/s^2) in the IMU frame and returns (events, estimate or None).
    Proprioception arrives through `add_proprio` no later than the samples
    that use it; every estimate uses only data stamped at or before its time.
    """

    def __init__(self, detector: OnsetDetector, conditioner: GyroConditioner, params: PipelineParams | None = None,
                 proprio: ProprioTrack | None = None):
        self.detector = detector
        self.cond = conditioner
        self.params = params or PipelineParams()
        self.method = self.params.method
        self.plane = Plane(self.params.plane_normal) if self.params.plane_normal is not None else None
        self.estimator = make_estimator(self.params, self.plane)
        self.eta = EtaSchedule(self.params.eta_table)
        self.proprio = proprio or ProprioTrack(sigma_p=self.params.ekf.sigma_p, sigma_v=self.params.ekf.sigma_v)
        self.tracking = False
        self.onset_t: float | None = None
        self.onset_p_tcp: np.ndarray | None = None
        self._v_onset = 0.0               # m/s, the TCP's speed at the onset (an arm already moving: IMPACT_TAU_S)
        self._t_prev: float | None = None
        self._wwT = np.zeros((3, 3))
        self._w_sum = np.zeros(3)
        self._n_w = 0
        self._t_out = -np.inf
        self._dt_sample = 1.0 / 6667.0
        self._angle = 0.0
        self._stamp_prev = np.nan
        self._rates = RateHistory()
        self._begin_t: float | None = None
        self._g_sat, self._a_sat = DEFAULT_SATURATION
        self.saturated = 0                   # samples of the current episode clipped at full scale
        self.saturated_since: float | None = None   # the stream has been mostly clipped since this time
        self._since_gyro_sat = 1 << 30       # samples since the last clipped gyro sample (across batches)

    def set_odr(self, odr_hz: float) -> str | None:
        """The IMU source's data rate (a board reports its own): the onset detector's band window
        follows it. A problem, if any, as one line (OnsetDetector.set_odr)."""
        return self.detector.set_odr(odr_hz)

    def set_saturation(self, gyro_rad_s: float, accel_m_s2: float) -> None:
        """Where the source clips (drivers.lsm6dsr.Scaling.saturation): samples at or beyond it are
        not measurements. A clipped gyro sample, and every filtered sample whose low-pass window
        holds it, is left out of the estimator; the episode counts them (ContactEstimate.saturated)."""
        self._g_sat, self._a_sat = float(gyro_rad_s), float(accel_m_s2)

    def add_proprio(self, t: float, p: np.ndarray, v: np.ndarray | None, R: np.ndarray, w: np.ndarray | None,
                    force: float = np.nan) -> None:
        self.proprio.add(t, p, v, R, w, force)

    @property
    def warm(self) -> bool:
        """The onset detector has its rest levels (OnsetDetector.warm): a contact can be detected."""
        return self.detector.warm

    def set_trigger_armed(self, armed: bool) -> None:
        """Arm or disarm the onset trigger (an approach arms it once the arm moves at constant speed)."""
        if not self.tracking:
            self.detector.armed = armed

    def set_arc_following(self, on: bool) -> None:
        """The controller follows an arc about the estimate (True) or not: see ContactEstimator.set_arc_radial_var."""
        self.estimator.set_arc_radial_var(self.params.arc_radial_sigma ** 2 if on else 0.0)

    def begin(self, t: float) -> None:
        """Start a contact episode at the first sample at or after t (s), without waiting for the
        trigger: the controller knows the tool touches and is about to move it (a tangential probe
        from rest)."""
        if not self.tracking:
            self._begin_t = float(t)

    def hold_bias(self, held: bool) -> None:
        """The controller says whether the tool touches something outside a contact episode (settling
        after a touch, backing off): its rotations then are not bias either."""
        self.cond.bias_held = held

    def _set_eta_uncertainty(self, force_n: float) -> None:
        """Away from the calibrated grip forces eta is extrapolated: tell the estimator how much less it is
        known, and which way it is off (EtaSchedule.prior)."""
        if force_n != force_n:                   # NaN: no grip force measured
            force_n = self.params.grip_force_n
        self.estimator.set_eta_prior(*self.eta.prior(force_n, self.params.ekf.eta_rel_std,
                                                     self.params.eta_rel_std_per_n))

    def _track_bias(self, t: np.ndarray, gyro: np.ndarray) -> None:
        """Bias tracking while idle, except while the gripper itself turns (its rate is not bias)."""
        if len(t) == 0:
            return
        if self.proprio.n:
            _, _, _, w_tcp, *_, ok = self.proprio.lookup(t[-1:])
            if ok[0] and float(w_tcp[0] @ w_tcp[0]) > TCP_TURNING_RAD_S ** 2:
                return
        self.cond.track_bias(t, gyro)

    def follow(self, new: EstimatorDirective, old: EstimatorDirective) -> None:
        """Do what `new` says, having done what `old` said: a new episode number releases the contact
        episode (and begins the next at `begin_t` when given), after which every setting is applied
        again; otherwise only the settings that changed."""
        fresh = new.episode != old.episode
        if fresh:
            self.release()
            if new.begin_t is not None:
                self.begin(new.begin_t)
        if fresh or new.armed != old.armed:
            self.set_trigger_armed(new.armed)
        if fresh or new.arc_following != old.arc_following:
            self.set_arc_following(new.arc_following)
        if fresh or new.bias_held != old.bias_held:
            self.hold_bias(new.bias_held)

    def release(self) -> None:
        """End the contact episode: back to bias tracking and an armed trigger."""
        self.tracking = False
        self.onset_t = None
        self.onset_p_tcp = None
        self._begin_t = None
        self.cond.freeze_bias(False)
        self.detector.rearm()
        self.set_arc_following(False)

    def process(self, batch: np.ndarray, force_output: bool = False) -> tuple[list[dict], ContactEstimate | None]:
        """A batch of samples; returns (events, the newest estimate emitted, or None)."""
        events, estimates = self.process_all(batch, force_output)
        return events, (estimates[-1] if estimates else None)

    def process_all(self, batch: np.ndarray, force_output: bool = False) -> tuple[list[dict], list[ContactEstimate]]:
        """A batch of samples; returns (events, every estimate due within it).

        Conditioning is vectorised over the whole batch (it is causal per sample); the
        estimator then advances in sub-blocks that end at each output time, so each
        estimate uses only samples at or before its own time, whatever the batch length.
        """
        events: list[dict] = []
        if len(batch) == 0:
            return events, []
        t, gyro, accel = batch[:, 0], batch[:, 1:4], batch[:, 4:7]
        gyro_clipped = np.abs(gyro).max(axis=1) >= self._g_sat
        clipped = gyro_clipped | (np.abs(accel).max(axis=1) >= self._a_sat)
        n_clipped = int(np.count_nonzero(clipped))
        if n_clipped >= SATURATED_BATCH_FRACTION * len(t):
            if self.saturated_since is None:
                self.saturated_since = float(t[int(np.argmax(clipped))])
        else:
            self.saturated_since = None
        # each filtered sample whose low-pass window holds a clipped gyro sample is tainted
        idx = np.arange(len(t))
        last = np.maximum.accumulate(np.where(gyro_clipped, idx, -(1 << 40)))
        since = np.where(last >= 0, idx - last, self._since_gyro_sat + idx + 1)
        tainted = since < self.cond.lpf_window
        self._since_gyro_sat = int(since[-1])
        start = 0
        if not self.tracking:
            if self._begin_t is not None:
                hit = int(np.searchsorted(t, self._begin_t, side="left"))
                hit = hit if hit < len(t) else -1
            else:
                hit = self.detector.process(t, accel, gyro)
            if hit < 0:
                self._track_bias(t, gyro)
                self.cond.lowpass(gyro)      # keep the filter history warm
                return events, []
            self._track_bias(t[:hit], gyro[:hit])
            p, v, _, _, var_v0, _, force_on, ok = self.proprio.lookup(t[hit:hit + 1])
            if not ok[0]:
                self.detector.rearm()        # no proprioception yet: cannot start
                self.cond.lowpass(gyro)
                return events, []
            commanded, self._begin_t = self._begin_t is not None, None
            self.cond.freeze_bias(True)
            self._set_eta_uncertainty(float(force_on[0]))    # eta's prior for the episode
            self.estimator.set_position_noise(self.proprio.sigma_p_effective())
            self.estimator.start(p[0], v[0])
            self.tracking = True
            self._stamp_prev = np.nan
            self._rates.start(float(t[hit]) - self.cond.group_delay_samples * self._dt_sample)
            self.onset_t = float(t[hit])
            self.onset_p_tcp = p[0].copy()
            # the speed beyond the velocity's own noise (3 sigma): from rest, none
            self._v_onset = max(float(np.linalg.norm(v[0])) - 3.0 * math.sqrt(max(float(var_v0[0]), 0.0)), 0.0)
            self._t_prev = float(t[hit])
            self._wwT[:] = 0.0
            self._w_sum[:] = 0.0
            self._n_w = 0
            self._angle = 0.0
            self._t_out = -np.inf
            self.saturated = 0
            start = hit
            events.append({"kind": "contact_onset", "t": self.onset_t, "p_tcp": p[0].tolist(), "commanded": commanded})
        w_f = self.cond.lowpass(gyro)[start:]
        ts = t[start:]
        if len(t) > 1:
            self._dt_sample = (t[-1] - t[0]) / (len(t) - 1)
        # The causal low-pass delays the gyro by its group delay; take proprioception at the
        # same (earlier) instant so that w and v describe the same moment. Still causal.
        delay = self.cond.group_delay_samples * self._dt_sample
        p, v, R, w_tcp, var_v, var_wt, force, ok, stamp = self.proprio.lookup(ts - delay, with_stamp=True)
        force = np.where(np.isnan(force), self.params.grip_force_n, force)
        eta = self.eta(force)
        w_obj = self.cond.object_rate_world(w_f, R, w_tcp, eta[:, None])
        # The positions as evidence (PositionEvidence) integrate the object's rotation up to each
        # TCP position. The fingertip's twist reaches the IMU `lag` late (below), so the twist read
        # now is the object's relative rotation at now - lag: each position pairs with the twist
        # read lag after it, and with the gripper's own rotation up to its own time. Unpaired, the
        # angle trails the displacement by rate x lag, and the lever arm reads long by lag / t
        # (MuJoCo arcs at 12 cm: 3-4 mm at 100 ms, 1.4 mm at 180 ms).
        lag = self.params.fingertip_lag_s
        shift = lag if self.estimator.lag_aligned_positions else 0.0
        if shift > 0:
            p_pos, _, _, w_tcp_pos, _, _, _, ok_pos, stamp = self.proprio.lookup(ts - delay - shift, with_stamp=True)
            w_pos = w_obj - w_tcp + w_tcp_pos
        else:
            p_pos, w_tcp_pos, w_pos, ok_pos = p, w_tcp, w_obj, ok
        # A proprioception sample is a position measurement at the first IMU sample that sees it
        # (extrapolated by less than one IMU period; later ones are not taken).
        new = np.diff(stamp, prepend=self._stamp_prev) != 0
        fresh = new & ((ts - delay - shift - stamp) <= FRESH_MAX_AGE_S) & ok_pos
        if self._v_onset > 0.0:
            # an arm moving at the onset: its displacement while the grasp takes up the motion is
            # not the pivot's (below, IMPACT_TAU_S); positions count from three time constants on
            # (the offset the take-up leaves is the regression's intercept)
            fresh &= stamp >= self.onset_t + 3.0 * IMPACT_TAU_S
        self._stamp_prev = float(stamp[-1])
        # A stale gripper rate enters the object rate as (1 - eta) * its error.
        var_w = (eta - 1.0) ** 2 * var_wt
        # A held TCP velocity was measured at its stamp (a derived one over the interval to it): it
        # pairs with the object's rate and the TCP's position then, not with those of each sample
        # that holds it. At 65 Hz that is up to a period of change: from a start at rest the held
        # velocity still reads zero while the object already turns, and the lever arm reads short.
        # The history holds the IMU's own rate in the world; the object's rate is made from its mean
        # with the gripper's rate of the same moment (a gripper rate extrapolated past a change
        # would enter it (eta - 1) times).
        ok &= ~tainted[start:]           # clipped at full scale: no measurement (set_saturation)
        self._rates.add((ts - delay)[ok], self.cond.object_rate_world(w_f[ok], R[ok], np.zeros(3), 1.0))
        p_v, tv, hv, var_v = self.proprio.velocity_at(ts - delay)
        # The fingertip's twist, which the IMU reads, lags the object's by the silicone's viscoelastic
        # time constant (the paper's "phase lag", Sec. III-B, which its eta leaves out): the twist
        # read at tv + lag is the object's at tv. The gripper's own rotation reaches the IMU at once.
        w_tcp_v = self.proprio.rate_at(tv)
        w_tcp_lag = self.proprio.rate_at(tv + lag) if lag > 0 else w_tcp_v
        # the span the velocity stands for, as much of it as has been measured by each sample
        h = np.clip(ts - delay - tv - lag, 0.0, hv)
        w_imu_v, n_avg = self._rates.mean(tv + lag - h, tv + lag + h, w_tcp_lag, self._dt_sample)
        w_v = w_tcp_v + eta[:, None] * (w_imu_v - w_tcp_lag)
        # A velocity measured before the touch is no evidence of the pivot: an arm already moving
        # into an edge moved the object with it (only a start from rest agrees with the model).
        var_v = np.where(tv < self._rates.t0, PRE_ONSET_VAR, var_v)
        # An arm already moving at the onset (an ongoing motion into an edge) first pushes through the
        # compliant grasp: the object takes up its rotation over the fingertip's and the grasp's give,
        # and until then the TCP's velocity is not the pivot's. On MuJoCo's block slid into its edge
        # at 20 mm/s the velocity's lever arm read 7x, 2x and 1.2x long over the first 5, 10 and 15 ms.
        # That part of the velocity is distrusted as it decays, IMPACT_TAU_S (nothing from rest).
        if self._v_onset > 0.0:
            v_push = self._v_onset * np.exp(-np.maximum(tv - self._rates.t0, 0.0) / IMPACT_TAU_S)
            var_v = var_v + v_push * v_push
        self._set_eta_uncertainty(float(force[-1]))
        # While the gripper itself turns the estimator needs its rate: eta's error scales only the
        # object's rotation relative to the gripper (ContactKF, and PositionEvidence for positions).
        tcp_turning = float(np.max(np.einsum("ij,ij->i", w_tcp, w_tcp))) > TCP_TURNING_RAD_S ** 2
        self.saturated += int(np.count_nonzero(clipped[start:]))
        if not tcp_turning:
            w_tcp_v = np.zeros_like(w_tcp_v)     # as w_tcp: the model takes every rotation as the object's
        if not ok.all():
            ts, w_obj, v, var_v, var_w, fresh = ts[ok], w_obj[ok], v[ok], var_v[ok], var_w[ok], fresh[ok]
            p_pos, w_pos, w_tcp_pos = p_pos[ok], w_pos[ok], w_tcp_pos[ok]
            w_v, w_tcp_v, p_v, n_avg = w_v[ok], w_tcp_v[ok], p_v[ok], n_avg[ok]
        estimates: list[ContactEstimate] = []
        if len(ts):
            dt = np.maximum(np.diff(ts, prepend=self._t_prev), 1e-6)
            rate = self.proprio.rate_hz()
            if rate == rate:       # not NaN
                self.estimator.set_correlation(max(1.0, 1.0 / (self._dt_sample * rate)))
            period = self.params.output_period_s
            estimates = self._advance(ts, dt, w_obj, (w_pos, p_pos, w_tcp_pos), v, var_v, var_w, fresh, tcp_turning,
                                      period, (w_v, w_tcp_v, p_v, n_avg))
        if force_output and not estimates and self._t_prev is not None and self._n_w:
            self._t_out = self._t_prev
            estimates.append(self._estimate(self._t_prev))
        return events, estimates

    def _advance(self, ts, dt, w_obj, positions: tuple, v, var_v, var_w, fresh, tcp_turning: bool,
                 period: float, paired: tuple) -> list[ContactEstimate]:
        """Advance the estimator in segments that end at each output time, and report at each.
        w_obj: the object's rate now (the angle and the axis); positions = (w, p, w_tcp): what the
        position evidence integrates, aligned with the TCP positions (process_all)."""
        w_pos, p, w_tcp = positions
        n = len(ts)
        ends: list[int] = []
        n_due, k0, t_out = 0, 0, self._t_out
        while k0 < n:
            due = int(np.searchsorted(ts, t_out + period, side="left"))
            k1 = n if due >= n else max(due + 1, k0 + 1)
            ends.append(k1)
            if due < n:
                t_out = float(ts[k1 - 1])
                n_due += 1
            k0 = k1
        snaps = self.estimator.advance(ends, n_due, dt, w_pos, p, v, var_v, var_w, fresh,
                                       w_tcp if tcp_turning else None, paired)
        estimates: list[ContactEstimate] = []
        k0 = 0
        for j, k1 in enumerate(ends):
            self._angle += rate_moments(w_obj[k0:k1], dt[k0:k1], self._wwT, self._w_sum)
            self._n_w += k1 - k0
            self._t_prev = float(ts[k1 - 1])
            if j < n_due:
                self._t_out = self._t_prev
                estimates.append(self._estimate(self._t_prev, snaps[j]))
            k0 = k1
        return estimates

    def _estimate(self, t: float, snap: Snapshot | None = None) -> ContactEstimate:
        """The output at t from the estimator's snapshot then (None: as it stands now)."""
        if snap is None:
            snap = self.estimator.snapshot()
        p_c, cov, stat = snap.p, snap.cov, snap.stat
        # Converged: the statistical uncertainty in the plane of rotation is small
        # (systematic floors such as eta's are reported, but do not shrink with data).
        if self.plane is not None:
            # The axis is the plane's normal, signed as the rotation; the in-plane variance is
            # the larger eigenvalue of the 2 x 2 in-plane covariance.
            sign, top = plane_rotation(stat, self.plane.E, self.plane.n, self._w_sum)
            axis = self.plane.n if sign > 0 else -self.plane.n
        else:
            # A rotation about one axis only: the contact is a line along it (edge, hinge),
            # unobservable along the axis whatever the gyro noise suggests; the covariance says so.
            axis, axes, cov, top = rotation_axes(self._wwT, self._w_sum, self._n_w, self.params.ekf.sigma_w ** 2, cov,
                                                 stat, MIN_AXIS_RATE_RAD_S ** 2, SECOND_AXIS_RATIO,
                                                 UNOBSERVED_STD_M ** 2)
            if axes == 1 and self.onset_p_tcp is not None:
                # Along the one axis the data say nothing yet: report the prior there, the TCP's
                # coordinate at onset, not wherever the filter's weak correlations have moved it
                # (a pen's tip, before its second axis is excited, is level with the TCP along it).
                p_c = p_c - float((p_c - self.onset_p_tcp) @ axis) * axis
            axis = axis if axes else None
        in_plane = math.sqrt(max(top, 0.0))
        # Converged only as far as the data fit the model: innovations larger than expected (the
        # first tens of ms of a soft grasp taking up the motion) widen the one-sigma by their
        # root ratio. On franky-sim's cutter the estimate read 4.7 mm in-plane at 66 ms while 39 mm
        # off (ratio 1.5, then 6), and its next step tripped the contact_jump stop.
        consistent = in_plane * math.sqrt(max(snap.consistency or 1.0, 1.0))
        return ContactEstimate(t=t, onset_t=self.onset_t, p=p_c, std=np.sqrt(np.maximum(cov.diagonal(), 0.0)),
                               cov=cov, axis=axis, converged=consistent < CONVERGED_STD_M and snap.steps > 100,
                               nis=snap.nis, steps=snap.steps, method=self.method, in_plane_std=in_plane,
                               angle_rad=self._angle, nis_ratio=snap.consistency,
                               onset_p_tcp=self.onset_p_tcp, saturated=self.saturated)
