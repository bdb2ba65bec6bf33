"""Contact pipeline: onset trigger -> gyro conditioning -> measurements -> estimator, on IMU batches, causally.

Used by the daemon's estimator thread and by `tecdard localize` alike. The pipeline owns the
episode: it finds the onset, conditions the gyro, leaves out what the chip clipped, hands each run
of samples to control.measurements for one `Samples` record, and reports the estimator's state at
each output time.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from tecdard.control import estimators
from tecdard.control.conditioning import GyroConditioner
from tecdard.control.estimators.base import UNOBSERVED_STD_M, Snapshot
from tecdard.control.estimators.kernels.api import output_ends, plane_rotation, rotation_axes, segment_moments
from tecdard.control.geometry import Plane
from tecdard.control.measurements import FINGERTIP_LAG_S, TCP_TURNING_RAD_S, EtaSchedule, Measurements, RigNoise
from tecdard.control.onset import BACKDATE_MAX_S, OnsetDetector
from tecdard.control.proprio import ProprioSample, ProprioTrack
from tecdard.drivers.lsm6dsr import Scaling
from tecdard.options import option, read_options
from tecdard.safejson import show

CONVERGED_STD_M = 0.005       # converged when the in-plane one-sigma (x the root NIS ratio above 1) is below this
MIN_AXIS_RATE_RAD_S = 1e-3
SECOND_AXIS_RATIO = 0.05      # a rotation about a 2nd axis this strong (by variance) makes 3D observable
# The LSM6DSR's clipping points at its default full scales (4000 dps, 16 g: 80.06 rad/s, 156.8 m/s^2),
# until a source says which scales it runs.
DEFAULT_SATURATION = Scaling().saturation
SATURATED_BATCH_FRACTION = 0.5    # a batch this clipped counts toward a clipped stream (a stuck or overloaded chip)
MAX_ETA = 100.0               # eta is 1-3 for real fingertips (the paper's 2.0 at 30 N)
MAX_GRIP_FORCE_N = 1000.0
MAX_ETA_ROWS = 100


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
    since_t: float | None = None       # with a new episode: samples stamped before this are an earlier episode's


@dataclass
class PipelineParams:
    """The `estimator` section's own options, and every estimator's (`options`: section -> options)."""
    method: str = option(estimators.DEFAULT, "the estimator (one of `tecdard localize --method`'s: ekf, paper-ekf, "
                                             "svd-geo, gd-geo, svd-diff, gd-diff)", max_len=64)
    plane_normal: np.ndarray | None = option(None, "world: when set, the interaction is planar about it and the "
                                                   "planar estimator is used", kind="optunitvec3")
    output_period_s: float = option(0.005, "contact estimates are emitted at most this often", unit="s", above=0.0,
                                    maxval=1.0)
    eta_table: list = option([(30.0, 2.0)], "[[grip force N, eta], ...]: the fingertip's transmission, calibrated "
                                            "(`tecdard calibrate-eta`; the paper's 2.0 at 30 N)", kind="custom",
                             shown="[[30, 2]]")
    grip_force_n: float = option(30.0, "the grip force when none is measured", unit="N", minval=0.0,
                                 maxval=MAX_GRIP_FORCE_N)
    eta_rel_std_per_n: float = option(0.02, "eta's relative uncertainty grows this much per N off its calibration",
                                      unit="1/N", minval=0.0, maxval=1.0)
    arc_radial_sigma: float = option(0.005, "distrust of the velocity along the lever arm while following an arc",
                                     unit="m/s", minval=0.0, maxval=1.0)
    fingertip_lag_s: float = option(FINGERTIP_LAG_S, "the fingertip twist's viscoelastic lag behind the object (a "
                                                     "rig's own, like eta)", unit="s", minval=0.0, maxval=0.05)
    bias_tau_s: float = option(0.5, "the gyro bias's tracking time constant at rest", unit="s", above=0.0)
    gyro_lpf_window: int = option(33, "samples of the gyro's causal moving average (about 5 ms at 6.7 kHz)",
                                  minval=1, maxval=2000)
    noise: RigNoise = field(default_factory=RigNoise)
    options: dict = field(default_factory=dict)


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
        self.estimator = estimators.build(self.method, self.params.options, self.plane)
        self.eta = EtaSchedule(self.params.eta_table)
        self.proprio = proprio or ProprioTrack(sigma_p=self.params.noise.sigma_p, sigma_v=self.params.noise.sigma_v)
        self.proprio.imu_mount = np.asarray(conditioner.R_tcp_imu, dtype=float)
        self.detector.guard.arm = self.proprio   # an accelerometer onset waits for the arm's states (onset_guard)
        self.measure = Measurements(conditioner, self.eta, self.proprio, self.params.grip_force_n,
                                    self.params.fingertip_lag_s)
        self.tracking = False
        self.on_onset = None       # (events so far) called at an onset, within its batch (the daemon's publisher)
        self.onset_t, self.onset_p_tcp = None, None    # s; (3,) m, world
        self._t_prev: float | None = None
        self._wwT = np.zeros((3, 3))
        self._w_sum = np.zeros(3)
        self._n_w = 0
        self._t_out = -np.inf
        self._dt_sample = 1.0 / 6667.0
        self._angle = 0.0
        self._begin_t: float | None = None
        self._since_t: float | None = None   # the episode's start: no onset from samples stamped before it
        self._pre = collections.deque()      # the last BACKDATE_MAX_S of idle batches (_keep_idle)
        self._g_sat, self._a_sat = DEFAULT_SATURATION
        self.saturated = 0                   # samples of the current episode clipped at full scale
        self.saturated_since: float | None = None   # the stream has been mostly clipped since this time
        self._since_gyro_sat = 1 << 30       # samples since the last clipped gyro sample (across batches)

    @classmethod
    def from_config(cls, section, R_tcp_imu: np.ndarray, odr_hz: float = 6667.0, method: str | None = None,
                    plane_normal=None) -> "ContactPipeline":
        """Every option of `estimator` is read here, and each estimator's own section by its module
        (estimators.read_options); `method`/`plane_normal` override the config's."""
        options = estimators.read_options(section)
        params = read_options(PipelineParams, section, eta_table=_eta_table(section),
                              # the rig's noise is stated once, in `ekf`'s section: the proprioception track
                              # and the rotation axis take it whichever estimator runs
                              noise=RigNoise.of(estimators.options_of("ekf", options)), options=options)
        if params.method not in estimators.names():
            raise section.error("method", f"expected one of {', '.join(estimators.names())}; got {show(params.method)}")
        params.method = method or params.method
        normal = plane_normal if plane_normal is not None else params.plane_normal
        params.plane_normal = np.array(normal) if normal is not None else None
        conditioner = GyroConditioner(R_tcp_imu, bias_tau_s=params.bias_tau_s, lpf_window=params.gyro_lpf_window)
        detector = OnsetDetector.from_config(section.section("onset"), odr_hz)
        return cls(detector, conditioner, params)

    # -- the sources' facts ---------------------------------------------------------------
    def set_odr(self, odr_hz: float) -> str | None:
        """The IMU source's data rate (a board reports its own): the onset detector's band window
        follows it. A problem, if any, as one line (OnsetDetector.set_odr)."""
        return self.detector.set_odr(odr_hz)

    @property
    def rate_notice(self) -> str | None:
        """What the onset detector cannot do at the IMU's rate, in one line (OnsetDetector.rate_notice)."""
        return self.detector.rate_notice

    def set_saturation(self, gyro_rad_s: float, accel_m_s2: float) -> None:
        """Where the source clips (drivers.lsm6dsr.Scaling.saturation): samples at or beyond it are
        not measurements. A clipped gyro sample, and every filtered sample whose low-pass window
        holds it, is left out of the estimator; the episode counts them (ContactEstimate.saturated)."""
        self._g_sat, self._a_sat = float(gyro_rad_s), float(accel_m_s2)

    def add_proprio(self, t: float, p: np.ndarray, v: np.ndarray | None, R: np.ndarray, w: np.ndarray | None,
                    grip_force_n: float = np.nan) -> None:
        self.proprio.add(t, p, v, R, w, grip_force_n)

    def add_command(self, t: float, qd) -> None:
        """A control tick's commanded joint rates (rad/s) at t: the daemon's own drive of the arm, which
        decides an accelerometer onset at once where it was steady (control.command_track)."""
        commands = self.detector.guard.commands
        if commands is not None:
            commands.add(t, qd)

    def add_sample(self, s: ProprioSample) -> None:
        """One robot state as the daemon's threads hand it over (control.proprio.ProprioSample)."""
        self.proprio.add(s.t, s.p_world, s.v_world, s.R_world_tcp, s.w_world, s.grip_force_n)

    @property
    def warm(self) -> bool:
        """The onset detector has its rest levels (OnsetDetector.warm): a contact can be detected."""
        return self.detector.warm

    # -- what the controller says ------------------------------------------------------------
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

    def follow(self, new: EstimatorDirective, old: EstimatorDirective) -> None:
        """Do what `new` says, having done what `old` said: a new episode number releases the contact
        episode (and begins the next at `begin_t` when given), after which every setting is applied
        again; otherwise only the settings that changed."""
        fresh = new.episode != old.episode
        if fresh:
            self.release()
            self._since_t = new.since_t
            if new.begin_t is not None:
                self.begin(new.begin_t)
        if fresh or new.armed != old.armed:
            self.set_trigger_armed(new.armed)
        if fresh or new.arc_following != old.arc_following:
            self.set_arc_following(new.arc_following)
        if fresh or new.bias_held != old.bias_held:
            self.hold_bias(new.bias_held)

    def release(self) -> None:
        """End the contact episode: back to bias tracking, and a trigger armed once the fingertip
        has settled (OnsetDetector.rearm: a touch and a stop ring it)."""
        self.tracking = False
        self.onset_t = None
        self.onset_p_tcp = None
        self._begin_t = None
        self._pre.clear()
        self.cond.freeze_bias(False)
        self.detector.rearm(settle=True)
        self.set_arc_following(False)

    # -- batches -------------------------------------------------------------------------------
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
        clipped, tainted = self._clipping(t, gyro, accel)
        if len(t) > 1:
            self._dt_sample = (t[-1] - t[0]) / (len(t) - 1)
        start, pre = 0, None
        if not self.tracking:
            start, pre = self._onset(t, gyro, accel, tainted, events)
            if start < 0:
                return events, []
            if self.on_onset is not None:  # the onset leaves before the episode's first estimates
                self.on_onset(events)
        w_f = self.cond.lowpass(gyro)[start:]
        ts, ok, acc = t[start:], ~tainted[start:], accel[start:]
        if pre is not None:                # an onset dated back into earlier batches
            ts, w_f, ok, acc = (np.concatenate([a, b]) for a, b in zip(pre, (ts, w_f, ok, acc)))
        samples = self.measure.take(ts, w_f, ok, acc, (self._dt_sample, self._t_prev))
        self._set_eta_uncertainty(self.measure.grip_force_now)
        self.saturated += int(np.count_nonzero(clipped[start:]))
        estimates: list[ContactEstimate] = []
        if len(samples):
            rate = self.proprio.rate_hz()
            if rate == rate:       # not NaN
                self.estimator.set_correlation(max(1.0, 1.0 / (self._dt_sample * rate)))
            estimates = self._advance(samples)
        if force_output and not estimates and self._t_prev is not None and self._n_w:
            self._t_out = self._t_prev
            estimates.append(self._estimate(self._t_prev))
        return events, estimates

    def _clipping(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clipped, tainted) per sample: at or beyond the source's full scale, and filtered samples whose
        low-pass window holds a clipped gyro sample. Keeps saturated_since: the stream has been mostly
        clipped since then (a stuck or overloaded chip)."""
        gyro_clipped = np.abs(gyro).max(axis=1) >= self._g_sat
        clipped = gyro_clipped | (np.abs(accel).max(axis=1) >= self._a_sat)
        if int(np.count_nonzero(clipped)) >= SATURATED_BATCH_FRACTION * len(t):
            if self.saturated_since is None:
                self.saturated_since = float(t[int(np.argmax(clipped))])
        else:
            self.saturated_since = None
        idx = np.arange(len(t))
        if not gyro_clipped.any():         # the usual batch: counting on from the last clipped sample
            since = self._since_gyro_sat + idx + 1
        else:
            last = np.maximum.accumulate(np.where(gyro_clipped, idx, -(1 << 40)))
            since = np.where(last >= 0, idx - last, self._since_gyro_sat + idx + 1)
        self._since_gyro_sat = int(since[-1])
        return clipped, since < self.cond.lpf_window

    def _explained(self, t: np.ndarray):
        """What the arm's own motion accounts for at each sample, IMU frame (ProprioTrack.explained):
        (the specific force of the TCP's acceleration and gravity (n, 3), the gripper's rate (n, 3),
        how far each may trail the arm (n,) (n,), |acceleration| (n,)); None before any state. The
        IMU's offset from the TCP is left out (its centripetal and tangential terms are millimetres
        per second squared at the gripper's rates)."""
        rows = self.proprio.explained(t)
        if rows is None:
            return None
        return rows[:, 0:3], rows[:, 3:6], rows[:, 6], rows[:, 7], rows[:, 8]

    def _keep_idle(self, t, w_f, ok, accel) -> None:
        """The last BACKDATE_MAX_S of idle samples, for an onset dated back into them, each batch with
        the gyro bias its filtered rate was made with (joined only when an onset is dated back)."""
        self._pre.append((t, w_f, ok, accel, self.cond.bias.copy()))
        while len(self._pre) > 1 and self._pre[1][0][0] <= float(t[-1]) - BACKDATE_MAX_S:
            self._pre.popleft()

    def _pre_rows(self):
        """The kept idle samples as one run: (t, w_f, ok, accel, the bias per sample)."""
        if not self._pre:
            return None
        return tuple(np.concatenate(x) for x in zip(*[(t, w, ok, a, np.tile(b, (len(t), 1)))
                                                      for t, w, ok, a, b in self._pre]))

    def _onset(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, tainted: np.ndarray, events: list):
        """Look for the onset in a batch while no episode runs (or begin the one the controller asked
        for): (the index in the batch it starts at, or -1; the earlier batches' samples it starts
        with, when dated back into them, else None). At the onset the estimator starts from the TCP then."""
        if self._begin_t is not None:
            hit = int(np.searchsorted(t, self._begin_t, side="left"))
            hit = hit if hit < len(t) else -1
            start_t = None
        else:
            first = 0 if self._since_t is None else int(np.searchsorted(t, self._since_t, side="left"))
            hit = self.detector.process(t, accel, gyro, self._explained(t), first)
            start_t = self.detector.onset_from_t if hit >= 0 else None
        if hit < 0:
            if not self.detector.pending:      # a twist that may be a contact is not bias
                self._track_bias(t, gyro)
            self._keep_idle(t, self.cond.lowpass(gyro), ~tainted, accel)   # the filter's history stays warm
            return -1, None
        detected_t = float(t[hit])
        start, pre = hit, None
        if start_t is not None and start_t < detected_t:
            # dated back: the gyro's bias as it stood then (it has tracked some of the twist since)
            start = int(np.searchsorted(t, start_t, side="left"))
            kept = self._pre_rows() if start == 0 else None
            if kept is not None and len(kept[0]):
                k = int(np.searchsorted(kept[0], start_t, side="left"))
                if k < len(kept[0]):
                    pre_t, pre_w, pre_ok, pre_a, pre_bias = (a[k:] for a in kept)
                    self.cond.bias = pre_bias[0].copy()
                    pre = (pre_t, pre_w + (pre_bias - self.cond.bias), pre_ok, pre_a)
        else:
            self._track_bias(t[:start], gyro[:start])
        t_on = float(pre[0][0]) if pre is not None else float(t[start])
        at = self.proprio.lookup(np.array([t_on]))
        p, v, var_v0, ok = at.p, at.v, at.var_v, at.ok
        if not ok[0]:
            self.detector.rearm()        # no proprioception yet: cannot start
            self._keep_idle(t, self.cond.lowpass(gyro), ~tainted, accel)
            return -1, None
        commanded, self._begin_t = self._begin_t is not None, None
        trigger = "commanded" if commanded else self.detector.fired_by
        self._pre.clear()
        self.cond.freeze_bias(True)
        self._set_eta_uncertainty(float(at.grip_force_n[0]))    # eta's prior for the episode
        self.estimator.set_position_noise(self.proprio.sigma_p_effective())
        self.estimator.start(p[0], v[0])
        self.tracking = True
        self.onset_t = t_on
        self.onset_p_tcp = p[0].copy()
        # the speed beyond the velocity's own noise (3 sigma): from rest, none
        v_onset = max(float(np.linalg.norm(v[0])) - 3.0 * math.sqrt(max(float(var_v0[0]), 0.0)), 0.0)
        self.measure.begin(self.onset_t, v_onset, self.onset_t - self.cond.group_delay_samples * self._dt_sample)
        self._t_prev = t_on
        self._wwT[:] = 0.0
        self._w_sum[:] = 0.0
        self._n_w = 0
        self._angle = 0.0
        # an onset dated back: the estimates from it on are made now, each from the samples up to its
        # own time (causal; the live daemon publishes them as one burst at the detection)
        self._t_out = -np.inf
        self.saturated = 0
        events.append({"kind": "contact_onset", "t": self.onset_t, "p_tcp": p[0].tolist(), "commanded": commanded,
                       "trigger": trigger, "detected_t": detected_t})
        return start, pre

    def _set_eta_uncertainty(self, force_n: float) -> None:
        """Away from the calibrated grip forces eta is extrapolated: tell the estimator how much less it is
        known, and which way it is off (EtaSchedule.prior)."""
        if force_n != force_n:                   # NaN: no grip force measured
            force_n = self.params.grip_force_n
        self.estimator.set_eta_prior(*self.eta.prior(force_n, self.params.noise.eta_rel_std,
                                                     self.params.eta_rel_std_per_n))

    def _track_bias(self, t: np.ndarray, gyro: np.ndarray) -> None:
        """Bias tracking while idle, except while the gripper itself turns (its rate is not bias)."""
        if len(t) == 0:
            return
        if self.proprio.n:
            w_tcp = self.proprio.rate_held(float(t[-1]))
            if w_tcp is not None and float(w_tcp @ w_tcp) > TCP_TURNING_RAD_S ** 2:
                return
        self.cond.track_bias(t, gyro)

    def _advance(self, samples) -> list[ContactEstimate]:
        """Advance the estimator in segments that end at each output time, and report at each. The
        segments and the rate moments after each are made in one compiled call each (output_ends,
        segment_moments): some 200 reports a second of recording cost a replay a tenth of its time
        as one call each."""
        ts, n = samples.t, len(samples)
        ends = np.empty(n, dtype=np.int64)
        m, n_due = output_ends(ts, self._t_out, self.params.output_period_s, ends)
        ends = ends[:m]
        snaps = self.estimator.advance(samples, ends, n_due)
        angles, wwT, w_sum = np.empty(m), np.empty((m, 3, 3)), np.empty((m, 3))
        segment_moments(samples.w, samples.dt, ends, self._wwT, self._w_sum, angles, wwT, w_sum)
        estimates: list[ContactEstimate] = []
        n_w0 = self._n_w
        for j in range(n_due):
            self._angle += float(angles[j])
            t = float(ts[ends[j] - 1])
            estimates.append(self._estimate(t, snaps[j], (wwT[j], w_sum[j], n_w0 + int(ends[j]))))
        for j in range(n_due, m):
            self._angle += float(angles[j])
        self._n_w = n_w0 + n
        self._t_prev = float(ts[n - 1])
        if n_due:
            self._t_out = float(ts[ends[n_due - 1] - 1])
        return estimates

    def _estimate(self, t: float, snap: Snapshot | None = None, moments=None) -> ContactEstimate:
        """The output at t from the estimator's snapshot then (None: as it stands now) and the rate
        moments then (wwT, w_sum, n_w; None: as they stand now)."""
        if snap is None:
            snap = self.estimator.snapshot()
        wwT, w_sum, n_w = (self._wwT, self._w_sum, self._n_w) if moments is None else moments
        p_c, cov, stat = snap.p, snap.cov, snap.stat
        # Converged: the statistical uncertainty in the plane of rotation is small
        # (systematic floors such as eta's are reported, but do not shrink with data).
        if self.plane is not None:
            # The axis is the plane's normal, signed as the rotation; the in-plane variance is
            # the larger eigenvalue of the 2 x 2 in-plane covariance.
            sign, top = plane_rotation(stat, self.plane.E, self.plane.n, w_sum)
            axis = self.plane.n if sign > 0 else -self.plane.n
        else:
            # A rotation about one axis only: the contact is a line along it (edge, hinge),
            # unobservable along the axis whatever the gyro noise suggests; the covariance says so.
            axis, axes, cov, top = rotation_axes(wwT, w_sum, n_w, self.params.noise.sigma_w ** 2,
                                                 cov, stat, MIN_AXIS_RATE_RAD_S ** 2, SECOND_AXIS_RATIO,
                                                 UNOBSERVED_STD_M ** 2)
            if axes == 1 and self.onset_p_tcp is not None:
                # Along the one axis the data say nothing yet: report the prior there, the TCP's
                # coordinate at onset, not wherever the filter's weak correlations have moved it
                # (a pen's tip, before its second axis is excited, is level with the TCP along it).
                p_c = p_c - float((p_c - self.onset_p_tcp) @ axis) * axis
            axis = axis if axes else None
        in_plane = math.sqrt(max(top, 0.0))
        # Converged only as far as the data fit the model: innovations larger than expected (a soft
        # grasp taking up the motion in the first tens of ms) widen the one-sigma by their root ratio.
        consistent = in_plane * math.sqrt(max(snap.consistency or 1.0, 1.0))
        return ContactEstimate(t=t, onset_t=self.onset_t, p=p_c, std=np.sqrt(np.maximum(cov.diagonal(), 0.0)),
                               cov=cov, axis=axis, converged=consistent < CONVERGED_STD_M and snap.steps > 100,
                               nis=snap.nis, steps=snap.steps, method=self.method, in_plane_std=in_plane,
                               angle_rad=self._angle, nis_ratio=snap.consistency,
                               onset_p_tcp=self.onset_p_tcp, saturated=self.saturated)


def _eta_table(section) -> list[tuple[float, float]]:
    """estimator.eta_table: [[grip force N, eta], ...], distinct forces, each within bounds."""
    rows = section.getrows("eta_table", [[30.0, 2.0]], width=2, max_rows=MAX_ETA_ROWS, what="[grip_force_N, eta]")
    for force, eta in rows:
        if not (0.0 < eta <= MAX_ETA and 0.0 <= force <= MAX_GRIP_FORCE_N):
            raise section.error("eta_table", f"eta must be in (0, {MAX_ETA:g}] and the force in "
                                              f"[0, {MAX_GRIP_FORCE_N:g}] N, got {[force, eta]}")
    if len({f for f, _ in rows}) != len(rows):
        raise section.error("eta_table", "a grip force appears twice")
    return [(float(f), float(e)) for f, e in rows]
