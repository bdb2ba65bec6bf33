"""`ekf`: our contact filter on the differential constraint v_tcp = w x (p_tcp - p_contact).

It takes, per IMU sample, the object's angular rate (world, conditioned: bias-free, filtered,
eta-scaled) and the TCP's position and velocity from proprioception (world, causal), all in one
control.measurements.Samples record, and estimates the contact point p_c. With a plane given it
works in that plane (2D), otherwise in 3D. Along a line contact (or the hinge axis) p_c is
unobservable: the estimate keeps the TCP's coordinate at onset there and the reported one-sigma
stays large. The model is stated in numpy in control/estimators/reference.py (`ekf-reference`);
its compiled run is kernels.run.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tecdard.control.estimators.base import (CONSISTENCY_TAU_S, UNOBSERVED_STD_M, ContactEstimator, EstimatorSpec,
                                             Snapshot)
from tecdard.control.estimators.kernels.api import (K_MIN, ekf_advance, ekf_segments, eta_weight, report_state,
                                                   report_states)
from tecdard.control.estimators.kernels.records import (RUN_PARAMS, STATUS, EkfState, Frame, Outputs, Window,
                                                        contiguous, record)
from tecdard.control.estimators.kernels.records import Samples as Run
from tecdard.control.estimators.positions import (MIN_RESIDUAL_SAMPLES, NO_EVIDENCE, POSITION_RESIDUAL_LIMIT,
                                                   PositionEvidence, position_var)
from tecdard.control.geometry import Plane
from tecdard.control.measurements import Samples
from tecdard.options import option, read_options

CONSISTENCY_WINDOW_S = 0.01  # the NIS ratio's window: at least the longest block (64 samples at 6.7 kHz)
_IDENTITY = np.eye(3)
_NO_NORMAL = np.zeros(3)
_NO_ALONG = np.zeros(9)         # 3D: no variance added along a plane normal
_NO_FRESH = np.zeros(0, dtype=bool)


def _or(a, b):
    """a, or b where a is None."""
    return b if a is None else a


@dataclass
class ContactKfParams:
    """The `estimator.ekf` section: our filter's noise model, SI units; variances per sample unless stated.
    The rig's noise is stated once, here: the proprioception track and the rotation axis take it whichever
    estimator runs."""
    sigma_w: float = option(0.01, "per-sample object-rate noise (raw gyro noise x eta)", unit="rad/s", above=0.0)
    sigma_p: float = option(5e-5, "TCP position noise (encoder grade)", unit="m", minval=0.0)
    sigma_v: float = option(1e-3, "reported TCP velocity noise", unit="m/s", above=0.0)
    q_c: float = option(1e-8, "the contact's random walk", unit="m^2/s", minval=0.0)
    p0_c: float = option(UNOBSERVED_STD_M ** 2, "the contact's prior variance", unit="m^2", above=0.0)
    gate_nis: float = option(16.3, "innovation gate, chi^2 (3 dof) at 0.999; 0 disables gating", minval=0.0)
    eta_rel_std: float = option(0.05, "eta's relative uncertainty at its calibration (+ estimator.eta_rel_std_per_n "
                                      "per N off it)", minval=0.0, maxval=1.0)
    max_block: int = option(64, "samples per collapsed update", minval=1, maxval=4096)
    use_positions: bool = option(True, "TCP displacements as evidence too (rigid-body displacement)")
    estimate_eta: bool = option(True, "eta's error as a state: the path's curvature corrects a wrong eta once the "
                                      "object has turned several degrees with the gripper still")
    eta_test_sigma: float = option(3.0, "the data must reject the scheduled eta by this many sigma to be used",
                                   minval=0.0)
    slip_radial_sigma: float = option(0.005, "distrust of the velocity along the lever arm once positions show a "
                                             "slip", unit="m/s", minval=0.0, maxval=1.0)
    arc_position_sigma: float = option(0.001, "the TCP positions' noise while following an arc (0: no evidence "
                                              "then)", unit="m", minval=0.0, maxval=0.1)

    @classmethod
    def from_config(cls, section) -> "ContactKfParams":
        return read_options(cls, section)


class ContactKfSettings:
    """The pipeline's settings and inputs as `ekf` takes them (ContactKF, and
    control.estimators.reference.ReferenceKF): each hook of ContactEstimator kept as the state the next update
    or episode reads, and an update's optional inputs made whole."""

    params: ContactKfParams
    positions: "PositionEvidence | None"

    def set_arc_radial_var(self, var_m2_s2: float) -> None:
        self.radial_var = var_m2_s2

    def set_eta_prior(self, mean: float, rel_std: float) -> None:
        self.eta_prior_mean, self.eta_rel_std = mean, rel_std

    def set_correlation(self, samples: float) -> None:
        self.corr_samples = samples

    def set_position_noise(self, sigma_m: float) -> None:
        self.sigma_p = max(float(sigma_m), self.params.sigma_p)
        if self.positions is not None:
            self.positions.var = position_var(self.sigma_p)

    def radial_var_now(self) -> float:
        """The distrust of the velocity along the lever arm, (m/s)^2: the arc follower's, or once the
        positions have shown the TCP moving relative to the object (PositionEvidence.broken: a
        push that stretches the grasp, a slide), the slip's. The slip runs along the lever arm, and
        taken as evidence it turns the estimate (docs/estimation.md: MuJoCo's pushes)."""
        if self.positions is not None and self.positions.broken:
            return max(self.radial_var, self.params.slip_radial_sigma ** 2)
        return self.radial_var

    def _episode_prior(self, p_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A new episode from the TCP at onset p_g: the origin (and the plane's), the position
        evidence restarted, eta's prior read from the settings; returns the state's prior (x, P):
        the contact at the onset TCP, k at its prior mean."""
        d = self.d
        self.origin = np.asarray(p_g, dtype=float).copy()
        if self.plane is not None:
            self.plane.origin = self.origin
        if self.positions is not None:
            self.positions.start()
        self.k_prior_mean = self.eta_prior_mean
        self.k_prior_var = self.eta_rel_std ** 2 if self.nk else 0.0
        x = np.append(np.zeros(d), [self.k_prior_mean] * self.nk)
        return x, np.diag([self.params.p0_c] * d + [self.k_prior_var] * self.nk)

    def _inputs(self, s: Samples) -> tuple[Run, bool]:
        """The record as `ekf` takes it (kernels.records.Samples), and whether it has positions (fresh).

        The position evidence integrates the rates and positions aligned with the fingertip's lag
        (Samples.w_pos, p_pos, w_tcp_pos). The held velocity pairs with the rate, the gripper's rate
        and the position from when it was measured; the rate there is a mean over n_avg samples, and
        every sample holding this velocity repeats it: one error, shared like the velocity's (corr).
        Without that pairing (n_avg None) the velocity is taken as of each sample."""
        n = len(s)
        var_v = np.full(n, self.params.sigma_v ** 2) if s.var_v is None else s.var_v
        var_w = np.zeros(n) if s.var_w is None else s.var_w
        w, p = _or(s.w_pos, s.w), _or(s.p_pos, s.p)
        w_tcp = _or(s.w_tcp_pos, s.w_tcp)
        w_tcp = np.zeros((n, 3)) if w_tcp is None else w_tcp
        if s.n_avg is None:
            w_v, w_tcp_v, p_v = w, w_tcp, p
        else:
            w_v, w_tcp_v, p_v = s.w_v, s.w_tcp_v, s.p_v
            var_w = var_w + self.params.sigma_w ** 2 * (max(self.corr_samples, 1.0) / s.n_avg - 1.0)
        fresh = _NO_FRESH if s.fresh is None else s.fresh
        return contiguous(Run(s.dt, w, w_tcp, p, s.v, w_v, w_tcp_v, p_v, var_v, var_w, fresh)), s.fresh is not None


class ContactKF(ContactKfSettings, ContactEstimator):
    """`ekf`: our filter on the same constraint, built for accuracy, honesty and speed.

    State x = [m, k]: k = eta_true / eta_used is the error of the scheduled eta and
    m = k c, with c the contact relative to the TCP at onset (plane coordinates when
    planar). The object's true rate is w_tcp + k (w - w_tcp) for the rate w computed
    with the scheduled eta, so with the gripper still
        v = k w x r0 - w x m
    is linear in the state (r0: the TCP relative to its onset position); a turning
    gripper adds w_tcp x (r0 - m / k), linearised about the estimate.

    Levers (see docs/estimation.md):
    - The TCP position and velocity are measured inputs (reported `tcp_vel` when the
      robot gives it) whose noise enters the measurement model, instead of states
      driven by large process noise.
    - A consistent measurement noise per sample: velocity noise including the
      staleness of causal proprioception, gyro noise through [r]x and position
      noise through [w]x, inflated by the number of IMU samples that share one
      proprioception sample (their errors are one error, not many).
    - Positions as evidence too (PositionEvidence).
    - Onset initialisation from the first block by an iterated update, and
      NIS gating of outliers.
    - Eta's error as a state with the calibration's uncertainty as its prior, leaning the
      way eta moves outside the calibrated grip forces (EtaSchedule.prior). The reported
      contact is the scheduled one (k at its prior mean, plus eta's uncertainty as a
      radial floor) until the data reject that by `eta_test_sigma`; then the free-eta
      estimate is blended in over kernels.ETA_BLEND_SIGMA, so the output does not jump.
    - Updates collapse each block of samples into one exactly equivalent
      measurement (H_eq^T H_eq = sum H^T R^-1 H), applied in Joseph form. A whole
      chunk of blocks, with the consistency window and the position evidence, is one
      compiled call (kernels.run.ekf_advance).
    """

    method = "ekf"

    def __init__(self, params: ContactKfParams | None = None, plane: Plane | None = None):
        self.params = params or ContactKfParams()
        self.sigma_p = self.params.sigma_p      # m, the TCP position noise this episode (set_position_noise)
        self.plane = plane
        self.d = d = 2 if plane is not None else 3
        # the report's variance along the plane's normal (unobservable), flattened for the kernel
        self._along_var = (UNOBSERVED_STD_M ** 2 * plane.nnT).ravel() if plane is not None else _NO_ALONG
        self._E = plane.E if plane is not None else _IDENTITY
        self._normal = plane.n if plane is not None else _NO_NORMAL
        self.nk = 1 if self.params.estimate_eta else 0   # k is a state, or held at its prior mean (cheaper)
        nx = d + self.nk
        self.x = np.zeros(nx)            # [m] or [m, k]
        self.P = np.eye(nx)
        self.origin = np.zeros(3)
        self.corr_samples = 1.0          # IMU samples per proprioception sample
        # eta's prior as the pipeline sets it from the grip force: the mean of k and its relative one-sigma
        # (raised away from eta's calibration, the mean moved off 1 outside the calibrated forces)
        self.eta_prior_mean = 1.0
        self.eta_rel_std = self.params.eta_rel_std
        self.k_prior_mean = 1.0          # as read at onset: k's prior, or the value k is held at
        self.k_prior_var = 0.0
        # Extra variance, (m/s)^2, of the TCP velocity along the lever arm. Set while a controller
        # follows an arc about the estimate: its own path error then moves the TCP along the lever
        # arm, the compliant grasp absorbs it, and that component is no evidence about the contact.
        # The tangential component (|v| = w |r|) stays, and the turning lever arm triangulates.
        self.radial_var = 0.0
        # The compiled run's state (kernels.ekf_advance): the counts and ratios (kernels.STATUS), the
        # lever arm at the last sample, and the consistency window: its start state and prior, its
        # information, and the per-sample NIS of its gated blocks.
        self._status = record(STATUS, consistency=1.0)
        self._r_last = np.zeros(d)
        self._win = Window(np.zeros(nx), np.eye(nx), np.eye(nx), np.zeros(nx))
        self._gated = np.empty(256)
        self._prm = record(RUN_PARAMS)
        self._frame = contiguous(Frame(self._E, self._normal, self.origin))
        self.positions = PositionEvidence(d, self.params.sigma_p, self.params.arc_position_sigma) \
            if self.params.use_positions else None
        self._ev = self.positions.ev if self.positions is not None else NO_EVIDENCE[d]

    @property
    def steps(self) -> int:
        """IMU samples taken this episode."""
        return int(self._status[0]["steps"])

    @property
    def rejected(self) -> int:
        """Samples the NIS gate rejected this episode."""
        return int(self._status[0]["rejected"])

    @property
    def nis(self) -> float:
        """The last gated sample's NIS."""
        return float(self._status[0]["nis"])

    @property
    def consistency(self) -> float:
        """The smoothed window NIS over its expectation (about 1 while the model holds; >= 1 scales the
        report, and the daemon's divergence stop reads it)."""
        return float(self._status[0]["consistency"])

    @property
    def k(self) -> float:
        """The eta ratio eta_true / eta_used, floored for division (its prior mean when not a state)."""
        return max(float(self.x[self.d]), K_MIN) if self.nk else self.k_prior_mean

    @property
    def c(self) -> np.ndarray:
        """The contact relative to the onset TCP with eta free (plane coordinates if planar), m."""
        return self.x[:self.d] / self.k

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        """Start an episode at the TCP state at onset; eta's prior is `eta_prior_mean`, `eta_rel_std` as set now."""
        self.x, self.P = self._episode_prior(p_g)
        self._status[0] = record(STATUS, consistency=1.0)[0]
        self._frame = contiguous(Frame(self._E, self._normal, self.origin))

    def update(self, samples: Samples) -> None:
        """A run of samples (control.measurements.Samples). What `ekf` takes of it: dt, the position
        evidence's rates and positions (w_pos, p_pos, w_tcp_pos; the gripper's rate zeros while still),
        the held velocity v with what it pairs with (w_v, w_tcp_v, p_v, n_avg) and its variance var_v
        (m/s)^2, the rate's extra variance var_w (rad/s)^2, and `fresh` (a new proprioception sample:
        a position measurement)."""
        run, use_fresh = self._inputs(samples)
        self._gated = ekf_advance(self._state(), self._gated, run, 0, len(samples), self._frame, self._run_params(),
                                  use_fresh, self.positions is not None)

    def advance(self, samples: Samples, ends, n_reports: int) -> list[Snapshot]:
        """ContactEstimator.advance in one compiled call (kernels.run.ekf_segments): the same segments
        and the same state after each as updates one by one, without their per-call cost."""
        run, use_fresh = self._inputs(samples)
        nx, d = len(self.x), self.d
        out = Outputs(np.empty((n_reports, nx)), np.empty((n_reports, nx, nx)), np.empty((n_reports, d)),
                      np.empty((n_reports, 3)))
        self._gated = ekf_segments(self._state(), self._gated, run, self._frame, self._run_params(), use_fresh,
                                   self.positions is not None, self.params.slip_radial_sigma ** 2,
                                   np.asarray(ends, dtype=np.int64), out)
        p, rep, stat = np.empty((n_reports, 3)), np.empty((n_reports, 3, 3)), np.empty((n_reports, 3, 3))
        report_states(out.x, out.P, out.r, out.s, d, *self._report_params(), p, rep, stat)
        return [Snapshot(p[j], rep[j], stat[j], int(out.s[j, 0]), float(out.s[j, 1]), float(out.s[j, 2]))
                for j in range(n_reports)]

    def _state(self) -> EkfState:
        """What the compiled run updates in place (kernels.records.EkfState)."""
        return EkfState(self.x, self.P, self._status, self._r_last, self._win, self._ev)

    def _run_params(self) -> np.ndarray:
        """The compiled run's parameters (kernels.records.RUN_PARAMS) as they stand now, in place."""
        prm = self.params
        self._prm[0] = (prm.q_c, self.corr_samples, self.sigma_p ** 2, prm.sigma_w ** 2, self.radial_var_now(),
                        prm.gate_nis, self.k_prior_mean, self.k_prior_var, prm.max_block, position_var(self.sigma_p),
                        CONSISTENCY_WINDOW_S, CONSISTENCY_TAU_S, MIN_RESIDUAL_SAMPLES, POSITION_RESIDUAL_LIMIT,
                        prm.arc_position_sigma ** 2)     # RUN_PARAMS' order
        return self._prm

    def eta_weight(self) -> float:
        """Weight of the free-eta estimate in the report: 0 while the data do not reject the calibration,
        and 0 when the eta they ask for is implausible (more than ETA_PRIOR_LIMIT of the calibration's
        sigmas off): that is the rigid pivot failing, not eta. An object sliding in the grasp while the
        TCP runs straight reads as k -> 0 (no curvature at all)."""
        if not self.nk:
            return 0.0
        return eta_weight(float(self.x[self.d]), float(self.P[self.d, self.d]), self.k_prior_mean, self.k_prior_var,
                          self.params.eta_test_sigma)

    def report(self, x=None, P=None, consistency=None, r_last=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c, reported covariance with the eta floor, the filter's own covariance), world, of the
        state now (or of the one given: x, P, the consistency ratio and the lever arm at its last
        sample, as ekf_segments keeps them).

        The scheduled estimate (k at its prior mean: the state conditioned on it, eta's uncertainty as
        a radial floor) until the data reject that; then the free-eta estimate c = m / k is blended in
        (kernels.report.report_state)."""
        if x is None:
            x, P, consistency, r_last = self.x, self.P, self.consistency, self._r_last
        eta, E, origin, along = self._report_params()
        return report_state(x, P, self.d, max(consistency, 1.0), r_last, *eta, E, origin, along)

    def _report_params(self) -> tuple:
        """What the report takes besides the state, as report_states takes it: (eta's figures: its
        relative variance, k's prior mean and variance, the blend's test sigma; the plane's basis, its
        origin, the variance along its normal)."""
        eta = np.array([(self.eta_rel_std / self.k_prior_mean) ** 2, self.k_prior_mean, self.k_prior_var,
                        self.params.eta_test_sigma])
        return eta, self._E, self.origin, self._along_var


ESTIMATORS = (EstimatorSpec("ekf", "our filter on the differential constraint (eta as a state, positions as "
                                   "evidence)", lambda options, plane: ContactKF(options, plane), "ekf", ContactKfParams),)
