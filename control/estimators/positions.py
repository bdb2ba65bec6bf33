"""The TCP's measured positions as evidence of a rigid pivot, beside the velocities (`ekf`'s PositionEvidence)."""
from __future__ import annotations

import numpy as np

from tecdard.control.estimators.kernels.api import (position_increment, position_reset, position_residual,
                                                    position_sums)
from tecdard.control.estimators.kernels.records import EVIDENCE_STATUS, Evidence, record

MIN_RESIDUAL_SAMPLES = 8       # position samples before the rigid-body residual test can speak
POSITION_RESIDUAL_LIMIT = 4.0  # residual / expectation above which positions are no evidence (slide)


def position_var(sigma_p: float) -> float:
    """The position evidence's noise variance, m^2 (floored: a noise-free rig still has rounding)."""
    return max(sigma_p, 1e-7) ** 2


class PositionEvidence:
    """What the TCP's measured positions say about the contact beyond its velocities.

    Integrating v = k w x (r - c) from a reference time (w: the object rate at the
    scheduled eta, k: the eta ratio, see ContactKF) gives
        r(t) = q + k G(t) - Theta(t) x m,    m = k c,
    with Theta = int w dt, G = int w x r dt (r: the TCP relative to the onset TCP) and
    q the true TCP at the reference time, unknown. Each proprioception sample is then a
    linear measurement of the filter's state (m, k) and of q, with its own independent
    noise sigma_p. q is marginalised in closed form (a regression with an intercept), so
    the marginal information on (m, k) is a Schur complement of running sums; it only
    grows, and each growth is handed to the filter as one exactly equivalent measurement.
    Reported velocities and positions carry independent noise, so nothing is counted
    twice (the gyro noise both share is small against either and is neglected). The
    k column is the curvature of the TCP's path against the gyro's angle: what tells a
    longer lever arm from a weaker fingertip once the object has turned a few degrees.

    Planar: Theta is the scalar angle and Theta x m is theta J m.

    A gripper that turns (w_tcp, its own rate) moves the TCP by w_tcp x (r - c) whatever
    eta is: with rel = w - w_tcp, v = w_tcp x r + k rel x r - rel x m - w_tcp x m / k, so
        r(t) - G_tcp(t) = q + k G(t) - Theta(t) x m,
    G_tcp = int w_tcp x r dt known, G = int rel x r dt and Theta = int (rel + w_tcp / k) dt,
    the 1/k linearised at the estimate. A gripper rate held between orientation samples
    lags while it changes; once it is steady the error it left is a constant, which the
    intercept q absorbs.

    The regression's residual checks the rigid-body model: when the TCP moves relative
    to the object (sliding in the grasp during a translational probe or an ongoing
    motion) displacements integrate that motion without bound, the residual grows far
    beyond the position noise, and the evidence is switched off for the episode.
    """

    def __init__(self, d: int, sigma_p: float, arc_sigma: float = 0.0):
        self.d = d
        nx = d + 1
        self.var = position_var(sigma_p)
        self.arc_var = arc_sigma ** 2    # m^2, the noise of positions taken while following an arc
        # the state the compiled run updates (kernels.records.Evidence): the counts (EVIDENCE_STATUS),
        # the angle (planar) or rotation vector integrated, G, the gripper's own part of it, the
        # regression's running sums (of the regressors X_k (d x (d+1)), X_k^T X_k, X_k^T y_k, y_k),
        # and the marginal information handed over so far (Lambda, xi; eta is the transmission ratio)
        self.ev = Evidence(record(EVIDENCE_STATUS), np.zeros(1 if d == 2 else 3), np.zeros(d), np.zeros(d),
                           np.zeros((d, nx)), np.zeros((nx, nx)), np.zeros(nx), np.zeros(d), np.zeros((nx, nx)),
                           np.zeros(nx))

    @property
    def n(self) -> int:
        """Position samples in the sums."""
        return int(self.ev.status[0]["n"])

    @property
    def s_yy(self) -> float:
        return float(self.ev.status[0]["s_yy"])

    @property
    def noise_var(self) -> float:
        """The noise variance of the positions in the sums: their own, or while following an arc the arc's."""
        return max(self.var, self.arc_var) if self.ev.status[0]["arc"] else self.var

    @property
    def broken(self) -> bool:
        """The rigid-body residual failed this episode: positions are no evidence until the next start."""
        return bool(self.ev.status[0]["broken"])

    def set_broken(self) -> None:
        self.ev.status[0]["broken"] = True

    def start(self) -> None:
        self.reset()
        self.ev.status[0]["broken"] = False
        self.ev.status[0]["arc"] = False

    def reset(self) -> None:
        """Restart the reference: no samples, integrals and sums zero (broken is kept)."""
        position_reset(self.ev)

    def add(self, dt: np.ndarray, w: np.ndarray, r: np.ndarray, fresh: np.ndarray, w_tcp: np.ndarray | None = None,
            k: float = 1.0) -> bool:
        """Integrate a chunk (w, and the gripper's own rate w_tcp: (n,) in-plane rates or (n, 3); r:
        (n, d)) and take the positions at the `fresh` samples (a new proprioception sample); True
        when any was taken. k: the eta ratio where the gripper's term is linearised."""
        ev = self.ev
        w = w.reshape(len(dt), -1)
        w_tcp = np.zeros(w.shape) if w_tcp is None else w_tcp.reshape(len(dt), -1)
        taken, s_yy = position_sums(ev, dt, w, w_tcp, 1.0 / k, r, fresh)
        ev.status[0]["n"] += taken
        ev.status[0]["s_yy"] += s_yy
        return taken > 0

    def increment(self) -> tuple[np.ndarray, np.ndarray]:
        """(dLambda, dxi): the growth of the marginal information on (m, k) since the last call."""
        return position_increment(self.ev, self.n, self.noise_var)

    def residual_ratio(self, k: float = 1.0) -> float:
        """Least-squares residual of the (q, m) regression at the eta ratio k, over its expectation (1 when
        the model holds). k is held, not fitted: a free k would absorb part of a slip in the grasp."""
        return position_residual(self.ev, self.s_yy, self.n, self.noise_var, k, MIN_RESIDUAL_SAMPLES)


# the compiled run's position evidence for a filter without it (never read)
NO_EVIDENCE = {d: PositionEvidence(d, 1.0).ev for d in (2, 3)}
