"""Contact-onset detection on IMU batches: accelerometer threshold, gyro threshold, accelerometer band energy,
and the fingertip's twist relative to the gripper; each on what the arm's own motion does not explain,
above the arm's own vibration, and (accelerometer) once the arm's states have not explained it."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tecdard.control.band_energy import band_at_rate
from tecdard.control.command_track import COMMAND_SETTLE_S, COMMAND_STEADY_RAD_S2, CommandTrack
from tecdard.control.conditioning import first_coincidence, mean0, moving_mean
from tecdard.control.onset_guard import FLOOR_K, PREDICT_HORIZON_S, REVERSAL_S, NoiseFloor, Predictor, StepGuard
from tecdard.control.proprio import ACCEL_WINDOW_S
from tecdard.options import option, read_options

MODES = ("any", "all")
BACKDATE_MAX_S = 0.3          # a twist onset is dated back at most this far
TWIST_HOLD_S = 0.2            # a twist fires once it has held one way this long (OnsetDetector._held)
# The twist trigger's default, rad/s: the fingertip turning relative to the gripper at 1.7 deg/s, over
# TWIST_WINDOW_S. Its noise over 33 samples of an LSM6DSR at 6.7 kHz is about 0.0015 rad/s (norm); a
# 12 cm lever turned at 2 cm/s twists a fingertip of eta 2 at 0.083 rad/s.
TWIST_THRESHOLD_RAD_S = 0.03
TWIST_WINDOW_S = 0.005
# A held object swings in the soft grasp when the arm starts and stops. MuJoCo's two-spring fingertip
# (sim.mujoco_source `carry`, eta 2) holding a 0.3 kg block 6 cm below the grasp reads up to 0.5 m/s^2
# per m/s^2 of the arm's acceleration beyond the arm's own: that much is allowed for the accelerometer.
# Its twist swings at up to 0.3 rad/s at 4 Hz, as large as a grasped hinge's when the arm starts to
# turn it (0.04-0.25 rad/s): an allowance that covered it would lose the hinge. The twist's hold
# (TWIST_HOLD_S) tells them apart instead.
SWING_ACCEL = 0.5
SWING_TAU_S = 0.1
SETTLE_LEVEL = 0.8            # settled: every condition under this fraction of its threshold for settle_s
# A grasped hinge turns the fingertip one way as long as the arm moves it; the arm's vibration turns it
# back and forth at tens of Hz. The hold is judged on the twist's mean over TWIST_HOLD_MEAN_S.
TWIST_HOLD_MEAN_S = 0.05
TWIST_FLOOR_K = 3.0           # ... and the twist's threshold is at least this many times that mean's moving RMS


@dataclass(frozen=True)
class OnsetOptions:
    """The `estimator.onset` section: what fires the trigger. The onset is judged on what the arm's own motion
    does not explain (docs/estimation.md); a condition set to none is off."""
    accel_threshold: float | None = option(0.4, "m/s^2 beyond the arm's own acceleration and gravity (the paper: "
                                                "0.4 from rest); none: off", unit="m/s^2", kind="optfloat",
                                           above=0.0)
    accel_axis: tuple | None = option(None, "judge the acceleration along this IMU axis only; none: its magnitude",
                                      kind="optunitvec3")
    gyro_threshold: float | None = option(None, "the fingertip's rate (the paper's, for mapping); none: off",
                                          unit="rad/s", kind="optfloat", above=0.0)
    band_threshold: float | None = option(None, "RMS acceleration in band_hz (the paper's, for heavy objects such "
                                                "as a book); none: off", unit="m/s^2", kind="optfloat", above=0.0)
    band_hz: tuple = option((40.0, 200.0), "the band of band_threshold: [lo, hi] (an IMU too slow for hi: lowered "
                                           "to 0.9 of half its rate, or off)",
                            unit="Hz", minval=1.0)
    mode: str = option("any", "any condition fires, or all of them within coincidence_s", choices=MODES)
    coincidence_s: float = option(0.02, "with mode all: the window the conditions must meet in", unit="s",
                                  above=0.0, maxval=1.0)
    rest_tau_s: float = option(0.5, "the rest levels' time constant", unit="s", above=0.0)
    warmup_s: float = option(0.1, "IMU data at rest before the trigger is armed (the daemon's READY waits for it)",
                             unit="s", minval=0.0)
    twist_threshold: float | None = option(TWIST_THRESHOLD_RAD_S, "the fingertip turning relative to the gripper "
                                                                  "(a contact that exists); none: off", unit="rad/s",
                                           kind="optfloat", above=0.0)
    settle_s: float = option(0.25, "after an episode or a task: still this long before the trigger arms", unit="s",
                             minval=0.0, maxval=10.0)
    swing_accel: float = option(SWING_ACCEL, "allowed per m/s^2 of the arm's acceleration (a held object's swing)",
                                unit="(m/s^2)/(m/s^2)", minval=0.0, maxval=10.0)
    proprio_lag_s: float = option(0.01, "how late the arm's states may be stamped: an accelerometer onset waits "
                                        "this plus the arm's acceleration fit for the states that may explain it "
                                        "(an acceleration step); 0: fires at once", unit="s", minval=0.0,
                                  maxval=0.1)
    mount_tolerance_deg: float = option(5.0, "how far the configured mount may be off (tecdard calibrate-mount "
                                             "measures it): the rate and acceleration it misattributes are "
                                             "allowed for", unit="deg", minval=0.0, maxval=30.0)
    predict_horizon_s: float = option(PREDICT_HORIZON_S, "the accelerometer is judged on what its remainder's own "
                                                          "past does not predict this far ahead (the arm's "
                                                          "narrow-band vibration taken off); 0: off", unit="s",
                                      minval=0.0, maxval=0.01)
    reversal_s: float = option(REVERSAL_S, "an accelerometer onset that swings back past its threshold this soon is "
                                           "decided without the arm's states (a step keeps its sign); 0: off",
                               unit="s", minval=0.0, maxval=0.05)
    command_settle_s: float = option(COMMAND_SETTLE_S, "the daemon driving the arm: an accelerometer onset is decided "
                                     "at its sample when the commanded joint rates held this long; 0: off",
                                     unit="s", minval=0.0, maxval=1.0)
    command_steady_rad_s2: float = option(COMMAND_STEADY_RAD_S2, "held: each tick's change of them over its period "
                                          "(the joints' sum) within this", unit="rad/s^2", above=0.0, maxval=10.0)
    floor_k: float = option(FLOOR_K, "the accelerometer's threshold is at least this many times the remainder's "
                                     "moving RMS (the arm's own vibration); 0: off", minval=0.0, maxval=50.0)


class OnsetDetector:
    """Fires at the first sample where the enabled conditions hold (`any`), or have all held
    within `coincidence_s` of each other (`all`):

    - `accel_threshold` (m/s^2): |accel - rest| (or its component on `accel_axis`, IMU frame);
    - `gyro_threshold` (rad/s): |gyro - rest|;
    - `band_threshold` (m/s^2 RMS): accelerometer energy in `band_hz` over one window of
      odr/band_hz[0] samples (the paper's way to catch heavy objects such as a book);
    - `twist_threshold` (rad/s): the gyro's mean over TWIST_WINDOW_S, less its rest: the
      fingertip turning relative to the gripper, which a contact that already exists (a grasped
      hinge the arm starts to turn) shows without any impact. It is the one condition whose onset
      is dated back (`onset_from_t`): to the last sample at which that mean was within twice its
      rms at rest (or a twentieth of the threshold), less the mean's group delay, at most
      BACKDATE_MAX_S before it fired.

    What the arm's own motion explains is taken off first when the caller knows it (`explained`: the
    specific force and the gripper's rate the robot's state predicts, IMU frame, and what each may be
    off by, which widens the thresholds): the arm's starts, stops and turns then are not contacts. The
    rest levels (the accelerometer's bias and the mount's error, the gyro's bias) follow the remainder
    while armed (`rest_tau_s`); nothing fires before `warmup_s` of data. After firing it stays disarmed
    until `rearm()`, and after `rearm(settle=True)` until the remainder has been still `settle_s`.

    On a real rig (control.onset_guard): the accelerometer's and the twist's thresholds are at least
    their moving noise floors (`floor`, `twist_floor`: the arm's vibration), the twist's hold is judged
    on its TWIST_HOLD_MEAN_S mean, and an accelerometer onset waits for the arm's states (`guard`)
    unless the daemon's own commands say the arm took no step (`guard.commands`). A configured mount
    off by up to `mount_tolerance` is allowed for.
    """

    def __init__(self, accel_threshold: float | None = 0.4, accel_axis=None, gyro_threshold: float | None = None,
                 band_threshold: float | None = None, band_hz=(40.0, 200.0), mode: str = "any",
                 coincidence_s: float = 0.02, rest_tau_s: float = 0.5, warmup_s: float = 0.1,
                 odr_hz: float = 6667.0, twist_threshold: float | None = None, settle_s: float = 0.25):
        if mode not in MODES:
            raise ValueError("mode: expected 'any' or 'all'")
        if accel_threshold is None and gyro_threshold is None and band_threshold is None and twist_threshold is None:
            raise ValueError("onset: enable at least one of accel_threshold, gyro_threshold, band_threshold, "
                             "twist_threshold")
        for name, v in (("accel_threshold", accel_threshold), ("gyro_threshold", gyro_threshold),
                        ("band_threshold", band_threshold), ("twist_threshold", twist_threshold)):
            if v is not None and v <= 0:
                raise ValueError(f"{name}: must be > 0")
        self.accel_threshold = accel_threshold
        self.accel_axis = None if accel_axis is None else np.asarray(accel_axis, float) / np.linalg.norm(accel_axis)
        self.gyro_threshold = gyro_threshold
        self.band_threshold = band_threshold
        self.twist_threshold = twist_threshold
        self.twist_window = max(1, int(round(TWIST_WINDOW_S * odr_hz)))
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))
        if not 0.0 < self.band_hz[0] < self.band_hz[1]:
            raise ValueError(f"band_hz: expected [lo, hi] with 0 < lo < hi, got [{self.band_hz[0]:g}, "
                             f"{self.band_hz[1]:g}]")
        self.odr_hz = float(odr_hz)
        self.band, self.rate_notice = None, None
        if band_threshold is not None:
            self.band, self.rate_notice = band_at_rate(self.band_hz, self.odr_hz)
        self.mode = mode
        self.coincidence_s = coincidence_s
        self.rest_tau_s = rest_tau_s
        self.warmup_s = warmup_s
        self.settle_s = settle_s
        # a held object swings in the soft grasp as the arm accelerates: the accelerometer's remainder
        # per m/s^2 of the arm's acceleration envelope is allowed for (none by default; the config's
        # swing_accel, SWING_ACCEL)
        self.swing_accel = 0.0
        self._swing_env, self._swing_t = 0.0, None
        self.rest_accel = None
        self.rest_gyro = None
        self._seen_s = 0.0
        self._last_true = {}
        self.armed = True
        self.settling = False          # rearm(settle=True): not until the remainder has been still settle_s
        self._still_since = None       # the remainder has been still since this time (settling)
        self._explaining = None        # whether the last batch came with what the arm's motion explains
        self._twist_hist = np.zeros((0, 3))
        self._twist_quiet_t = -np.inf  # the last time the twist's mean was within its noise
        self._twist_ms = 0.0           # the twist's mean square at rest, (rad/s)^2
        self._candidate = None         # a twist holding: (since, its direction, the quiet time before it)
        self._quiet = np.zeros(0, dtype=int)
        self.mount_tolerance = 0.0     # rad the configured mount may be off (from_config: mount_tolerance_deg)
        self._rest_expl = None         # the explained (force, rate) means the rest levels were learned under
        self._slow_hist = np.zeros((0, 3))   # the twist's TWIST_HOLD_MEAN_S mean's history
        self.floor = NoiseFloor()      # the accelerometer remainder's moving floor (from_config: floor_k)
        self.twist_floor = NoiseFloor(TWIST_FLOOR_K)   # the twist's hold mean's: the arm's vibration turning it
        self.predictor = Predictor(0.0, odr_hz)   # its prediction from its own past (from_config: predict_horizon_s)
        self._x_a = self._x_g = None   # the batch's accelerometer remainder (the predictor learns it), the guard's
        self._dev_a = self._dev_guard = None   # its magnitude judged (the prediction's error), and the guard's
        self._thr_a = self._thr_w = 0.0    # its and the twist's thresholds per sample (the moving floors)
        self.guard = StepGuard()       # an accelerometer onset waits for the arm's states (from_config, pipeline)
        self.onset_from_t: float | None = None    # the fired onset dated back (twist), else None
        self.fired_by: str | None = None          # the condition that fired ("accel", "twist", ...)

    def set_odr(self, odr_hz: float) -> str | None:
        """The source's data rate changed (a board's status packet): the twist's window and the
        band-energy window follow it (band_at_rate). Returns what the band condition cannot do at
        the new rate, in one line, or None."""
        odr_hz = float(odr_hz)
        if odr_hz == self.odr_hz:
            return None
        self.odr_hz = odr_hz
        self.twist_window = max(1, int(round(TWIST_WINDOW_S * odr_hz)))
        self.predictor.set_odr(odr_hz)
        self.rate_notice = None
        if self.band_threshold is None:
            return None
        self.band, self.rate_notice = band_at_rate(self.band_hz, odr_hz)
        return self.rate_notice

    @classmethod
    def from_config(cls, section, odr_hz: float = 6667.0) -> "OnsetDetector":
        o = read_options(OnsetOptions, section)
        if len(o.band_hz) != 2 or not o.band_hz[0] < o.band_hz[1]:
            # a setting's own consistency; whether it fits under the IMU's rate is the rate's business
            # (band_at_rate): a recording or a board at any rate is taken, the band condition adapted or off
            raise section.error("band_hz", "expected [lo, hi] with lo < hi, got ["
                                + ", ".join(f"{float(x):g}" for x in o.band_hz) + "]")
        try:
            det = cls(accel_threshold=o.accel_threshold, accel_axis=o.accel_axis, gyro_threshold=o.gyro_threshold,
                      band_threshold=o.band_threshold, band_hz=tuple(o.band_hz), mode=o.mode,
                      coincidence_s=o.coincidence_s, rest_tau_s=o.rest_tau_s, warmup_s=o.warmup_s, odr_hz=odr_hz,
                      twist_threshold=o.twist_threshold, settle_s=o.settle_s)
        except ValueError as exc:         # "accel_threshold: must be > 0": the key, then the problem
            key, _, problem = str(exc).partition(": ")
            raise section.error(key, problem) from None
        det.swing_accel = o.swing_accel
        det.guard.lag_s = o.proprio_lag_s
        det.guard.reversal_s = o.reversal_s
        if o.command_settle_s > 0.0:
            det.guard.commands = CommandTrack(o.command_settle_s, o.command_steady_rad_s2)
        det.floor.k = o.floor_k
        det.predictor = Predictor(o.predict_horizon_s, odr_hz)
        det.mount_tolerance = math.radians(o.mount_tolerance_deg)
        return det

    def rearm(self, settle: bool = False) -> None:
        """Start looking for the next onset; rest levels keep their last values. With `settle`
        (after a contact episode or a task) only once the remainder has been still `settle_s`:
        the fingertip rings and the grasp re-seats after a touch and a stop."""
        self.armed = True
        self._last_true = {}
        self.onset_from_t = None
        self.fired_by = None
        self._candidate = None
        self.guard.clear()
        if settle and self.settle_s > 0.0:
            self.settling = True
            self._still_since = None

    def _restart(self) -> None:
        """Learn the rest levels afresh (the remainder changed meaning: the arm's motion is, or is no
        longer, taken off)."""
        self.rest_accel = None
        self.rest_gyro = None
        self._rest_expl = None
        self._seen_s = 0.0
        self._twist_hist = np.zeros((0, 3))
        self._slow_hist = np.zeros((0, 3))
        self._twist_quiet_t = -np.inf
        self._twist_ms = 0.0
        self._candidate = None
        self.guard.clear()
        self.predictor.reset()
        self.twist_floor.restart()

    def _swing(self, t: np.ndarray, a_arm: np.ndarray) -> np.ndarray:
        """The envelope of the arm's acceleration (n,), m/s^2: its running maximum, decaying with
        SWING_TAU_S (a held object's swing in the soft grasp rings down about that fast)."""
        t0 = float(t[0])
        scaled = a_arm * np.exp((t - t0) / SWING_TAU_S)
        prev = self._swing_env * math.exp(-(t0 - self._swing_t) / SWING_TAU_S) if self._swing_t is not None else 0.0
        env = np.maximum.accumulate(np.maximum(scaled, prev)) * np.exp(-(t - t0) / SWING_TAU_S)
        self._swing_env, self._swing_t = float(env[-1]), float(t[-1])
        return env

    def _twist(self, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The gyro remainder's causal means over twist_window samples and over TWIST_HOLD_MEAN_S, less
        its rest level ((n, 3) each)."""
        out, self._twist_hist = moving_mean(self._twist_hist, gyro, self.twist_window)
        slow_n = max(self.twist_window, int(round(TWIST_HOLD_MEAN_S * self.odr_hz)))
        slow, self._slow_hist = moving_mean(self._slow_hist, gyro, slow_n)
        return out - self.rest_gyro, slow - self.rest_gyro

    def _conditions(self, t: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None, allow_a=0.0,
                    allow_w=0.0, twist=None) -> tuple[dict, dict]:
        """(condition -> fired per sample, condition -> its value over its threshold per sample).
        allow_a, allow_w: what the explained motion may be off by, per sample (m/s^2, rad/s); twist:
        None, or the batch's twist (_twist, (n, 3)) and its norm (n,)."""
        out, level = {}, {}
        self._dev_a = self._dev_guard = self._x_a = self._x_g = None
        if self.accel_threshold is not None:
            # what the remainder's own past does not predict (Predictor: the arm's vibration taken off)
            self._x_a = x = accel - self.rest_accel     # and, on accel_axis where set, the guard's (a reversal)
            self._x_g = x if self.accel_axis is None else (x @ self.accel_axis)[:, None] * self.accel_axis
            dev = self.predictor.error(self._x_a)
            mag = self._magnitude(dev)
            self._dev_a, self._thr_a = mag, self.accel_threshold_now()
            if self.predictor.on:
                # an acceleration step's prediction overshoots as the past catches up with it: the
                # guard weighs a candidate's peak in both views, and takes the smaller
                self._dev_guard = np.stack([mag, self._magnitude(self._x_a)])
                self._thr_a = np.maximum(self._thr_a, self.floor.recent(mag, self.odr_hz))
            level["accel"] = mag / (self._thr_a + allow_a + self.guard.mask(t))
        if self.gyro_threshold is not None and gyro is not None:
            dev = gyro - self.rest_gyro
            level["gyro"] = np.sqrt(np.einsum("ij,ij->i", dev, dev)) / (self.gyro_threshold + allow_w)
        if twist is not None:
            self._thr_w = thr_w = self.twist_floor.threshold(self.twist_threshold) + allow_w
            level["twist"] = twist[1] / thr_w
        if self.band is not None:
            level["band"] = np.sqrt(self.band.process(accel - self.rest_accel)) / self.band_threshold
        for name, x in level.items():
            out[name] = x > 1.0
        if twist is not None:
            out["twist"] = self._held(t, twist[0], out["twist"], 0.5 * thr_w, twist[2])
        return out, level

    def _magnitude(self, dev: np.ndarray) -> np.ndarray:
        """|dev| per sample (n,), or its component on accel_axis."""
        if self.accel_axis is not None:
            return np.abs(dev @ self.accel_axis)
        return np.sqrt(np.einsum("ij,ij->i", dev, dev))

    def _held(self, t: np.ndarray, tw: np.ndarray, over: np.ndarray, floor, slow: np.ndarray) -> np.ndarray:
        """The twist fires once it has held one way for TWIST_HOLD_S: over its threshold at the start,
        then its TWIST_HOLD_MEAN_S mean (`slow`) never under `floor` (half of it) along that direction
        (a grasped hinge keeps twisting one way as long as the arm moves; a held object swinging in the
        grasp turns back within half its period). True at the sample where the hold completes."""
        n = len(t)
        fired = np.zeros(n, dtype=bool)
        floor = np.broadcast_to(floor, (n,))
        i = 0
        while i < n:
            if self._candidate is None:
                up = np.flatnonzero(over[i:])
                if not len(up):
                    break
                i += int(up[0])
                before = self._quiet[self._quiet < i]        # where the twist was last within its noise
                quiet_t = float(t[before[-1]]) if len(before) else self._twist_quiet_t
                self._candidate = (float(t[i]), tw[i] / np.linalg.norm(tw[i]), quiet_t)
            t0, u, _ = self._candidate
            drop = np.flatnonzero(slow[i:] @ u < floor[i:])
            held = np.flatnonzero(t[i:] - t0 >= TWIST_HOLD_S)
            k_drop = int(drop[0]) if len(drop) else n
            k_held = int(held[0]) if len(held) else n
            if k_held < n and k_held <= k_drop:
                fired[i + k_held] = True
                break
            if k_drop >= n - i:
                break
            self._candidate = None
            i += k_drop + 1
        return fired

    @property
    def pending(self) -> bool:
        """A twist is holding (TWIST_HOLD_S): neither the rest levels nor the gyro's bias may learn from it."""
        return self._candidate is not None or self.guard.waiting

    @property
    def warm(self) -> bool:
        """Rest levels set from `warmup_s` of data: an onset can fire from the next batch on."""
        return self.rest_accel is not None and self._seen_s >= self.warmup_s

    def process(self, t: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None = None, explained=None,
                first: int = 0) -> int:
        """Index into the batch of the first sample that fires, or -1. `explained`: None, or (specific
        force (n, 3), gyro rate (n, 3), their allowances (n,) m/s^2 and (n,) rad/s, the arm's own
        acceleration's magnitude (n,) m/s^2) that the arm's own motion accounts for, IMU frame, taken
        off the samples first. Samples before index `first` never fire (an earlier episode's)."""
        n = len(t)
        if n == 0:
            return -1
        explaining = explained is not None
        if explaining != self._explaining:
            if self._explaining is not None:
                self._restart()
            self._explaining = explaining
        allow_a = allow_w = 0.0
        if explaining:
            accel = accel - explained[0]
            if gyro is not None:
                gyro = gyro - explained[1]
            swing = self._swing(t, explained[4])
            # the fit trails the arm by its half window, and stamps may be proprio_lag_s late on top;
            # a mount off by mount_tolerance misattributes that angle of the arm's acceleration and rate
            lag_gain = 1.0 + 2.0 * self.guard.lag_s / ACCEL_WINDOW_S
            allow_a = lag_gain * explained[2] + self.swing_accel * swing
            allow_w = lag_gain * explained[3]
            if self.mount_tolerance > 0.0 and self._rest_expl is not None:
                # what the arm's motion and attitude do since the rest levels were learned, times how far
                # the mount may be off: the part of it a wrong mount puts on the wrong axes
                df, dw = explained[0] - self._rest_expl[0], explained[1] - self._rest_expl[1]
                allow_a = allow_a + self.mount_tolerance * np.sqrt(np.einsum("ij,ij->i", df, df))
                allow_w = allow_w + self.mount_tolerance * np.sqrt(np.einsum("ij,ij->i", dw, dw))
        if self.rest_accel is None:
            self.rest_accel = mean0(accel)
            self.rest_gyro = mean0(gyro) if gyro is not None else np.zeros(3)
            self._rest_expl = None if not explaining else (mean0(explained[0]), mean0(explained[1]))
        self._quiet, twist = np.zeros(0, dtype=int), None
        if self.twist_threshold is not None and gyro is not None:
            tw, slow = self._twist(gyro)
            twist = tw, np.sqrt(np.einsum("ij,ij->i", tw, tw)), slow
            # where the twist is within twice its own noise (its rms at rest), or a twentieth of the threshold
            quiet_level = max(2.0 * math.sqrt(self._twist_ms), 0.05 * self.twist_threshold)
            self._quiet = np.flatnonzero(twist[1] <= quiet_level)
        conds, level = self._conditions(t, accel, gyro, allow_a, allow_w, twist)
        if self.settling or not self.armed:
            self._candidate = None        # a twist counts only from when the trigger may fire
        quiet = self._quiet
        hit, by = -1, None
        if self.guard.waiting and self.armed and not self.settling:
            hit, by = self.guard.decide(t, self._peak_dev(), self.swing_accel, self._x_g), "accel"  # nothing else fires
        elif self.settling:
            self._settle(t, level, twist)
        elif self.armed and self._seen_s >= self.warmup_s and conds:
            if first > 0:
                conds = {k: np.where(np.arange(n) >= first, v, False) for k, v in conds.items()}
            if self.mode == "any":
                fired = np.logical_or.reduce(list(conds.values()))
                idx = np.flatnonzero(fired)
                hit = int(idx[0]) if len(idx) else -1
            else:
                hit = self._coincidence(t, conds)
            if hit >= 0:
                by = next(k for k, v in conds.items() if v[hit])
                if by == "accel" and self.guard.applies(bool(self._explaining), self.mode):
                    self.guard.start(float(t[hit]), float(np.broadcast_to(self._thr_a, (n,))[hit]
                                                          + np.broadcast_to(allow_a, (n,))[hit]),
                                     self.guard.past(self._x_g, hit, self.odr_hz))
                    hit = self.guard.decide(t, self._peak_dev(), self.swing_accel, self._x_g)
        if hit >= 0:
            self._fire(t, hit, by)
        if len(quiet):
            self._twist_quiet_t = float(t[quiet[-1]])
        if hit < 0 and not self.pending:
            dt = float(t[-1] - t[0]) if n > 1 else 0.0
            tau = self.settle_s / 4.0 if self.settling else self.rest_tau_s
            # a cumulative mean until tau of data has been seen, then exponential forgetting: the
            # first levels are not one batch's (an arm starting as the recording starts)
            alpha = max((dt + 1e-4) / (self._seen_s + dt + 1e-4), 1.0 - math.exp(-(dt + 1e-4) / tau))
            self.rest_accel = self.rest_accel + alpha * (mean0(accel) - self.rest_accel)
            if gyro is not None:
                self.rest_gyro = self.rest_gyro + alpha * (mean0(gyro) - self.rest_gyro)
            if explaining and self._rest_expl is not None:
                # the explained force and rate the rest levels were learned under, with them
                f0, w0 = self._rest_expl
                self._rest_expl = (f0 + alpha * (mean0(explained[0]) - f0), w0 + alpha * (mean0(explained[1]) - w0))
            if twist is not None and not self.settling:
                ms = float(np.mean(twist[1] ** 2))
                self._twist_ms = ms if self._twist_ms == 0.0 else self._twist_ms + alpha * (ms - self._twist_ms)
            self._seen_s += dt
        if hit < 0 and not self.pending and self._dev_a is not None:
            self.floor.learn(t, self._dev_a, self.odr_hz)
        if hit < 0 and not self.pending and twist is not None and self._explaining:   # the arm's turning taken off
            self.twist_floor.learn(t, np.linalg.norm(twist[2], axis=1), self.odr_hz)
        if self._x_a is not None:
            self.guard.observe(self._x_g, self.odr_hz)
            if hit < 0 and not self.pending and self.armed and not self.settling:
                if self.predictor.learn(self._x_a):     # the arm's own vibration, armed: nothing of a contact
                    self.floor.restart()
            else:
                self.predictor.gap()
        return hit

    def _peak_dev(self):
        """What the step guard weighs a candidate's peak on: the prediction's error and the remainder
        itself ((2, n): the smaller peak counts), or the error alone without a predictor."""
        return self._dev_a if self._dev_guard is None else self._dev_guard

    def _fire(self, t: np.ndarray, hit: int, by: str) -> None:
        self.armed = False
        self.fired_by = by
        self.onset_from_t = None
        if self.guard.decided_t is not None:     # one the guard had to clear: at the candidate's sample
            self.onset_from_t, self.guard.decided_t = self.guard.decided_t, None
        elif self._candidate is not None and self._candidate[0] <= float(t[hit]):
            # a twist holding since before (any condition may fire first: a hinge's friction
            # breaking away): from where it left its noise, less its mean's group delay
            since = self._candidate[2] - 0.5 * (self.twist_window - 1) / self.odr_hz
            self.onset_from_t = max(since, float(t[hit]) - BACKDATE_MAX_S)
        self._candidate = None

    def accel_threshold_now(self) -> float:
        """The accelerometer's threshold, m/s^2: the configured one, or the noise floor's where the
        arm's vibration or the sensor's noise is larger (NoiseFloor)."""
        return self.floor.threshold(self.accel_threshold)

    def _settle(self, t: np.ndarray, level: dict, twist) -> None:
        """While settling: the remainder still (every condition under SETTLE_LEVEL of its threshold,
        the accelerometer's with its moving floor, the twist's on its hold mean) for settle_s ends it."""
        if twist is not None and "twist" in level:      # the hold mean: the arm's dither turns it to and fro
            level = {**level, "twist": np.linalg.norm(twist[2], axis=1) / self._thr_w}
        still = np.logical_and.reduce([x < SETTLE_LEVEL for x in level.values()])
        moving = np.flatnonzero(~still)
        if len(moving):
            self._still_since = float(t[moving[-1]]) if moving[-1] < len(t) - 1 else None
            if self._still_since is None:
                return
        elif self._still_since is None:
            self._still_since = float(t[0])
        if float(t[-1]) - self._still_since >= self.settle_s:
            self.settling = False

    def _coincidence(self, t: np.ndarray, conds: dict) -> int:
        """First sample at which every condition has been true within coincidence_s."""
        return first_coincidence(t, conds, self._last_true, self.coincidence_s)
