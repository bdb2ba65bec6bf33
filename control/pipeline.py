"""Contact pipeline: onset trigger -> gyro conditioning -> differential-constraint EKF, on IMU batches."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from control.conditioning import GyroConditioner
from control.ekf import ContactEKF, EkfParams
from control.onset import OnsetDetector

PROPRIO_HISTORY = 64          # proprioception samples kept for causal lookup
OUTPUT_PERIOD_S = 0.005       # estimates are emitted at most at 200 Hz
CONVERGED_STD_M = 0.005       # converged when the in-plane one-sigma is below this
MIN_AXIS_RATE_RAD_S = 1e-3


@dataclass
class ContactEstimate:
    t: float                  # s, time of the last IMU sample used
    onset_t: float            # s
    p: np.ndarray             # contact / hinge point, world, m
    std: np.ndarray           # one-sigma per world axis, m
    axis: np.ndarray | None   # rotation axis estimate, world unit (None until excited)
    converged: bool
    nis: float
    steps: int

    def to_json(self, method: str) -> dict:
        return {"t": self.t, "onset_t": self.onset_t, "p": self.p.tolist(), "std": self.std.tolist(),
                "converged": self.converged, "method": method,
                "axis": None if self.axis is None else self.axis.tolist()}


class ProprioHistory:
    """Recent TCP states (t, p, v, R, w) for causal lookup: a sample at time t sees only states at or before t."""

    def __init__(self, size: int = PROPRIO_HISTORY):
        self.size = size
        self.t = np.full(size, np.inf)
        self.p = np.zeros((size, 3))
        self.v = np.zeros((size, 3))
        self.R = np.tile(np.eye(3), (size, 1, 1))
        self.w = np.zeros((size, 3))
        self.n = 0

    def add(self, t: float, p: np.ndarray, v: np.ndarray, R: np.ndarray, w: np.ndarray) -> None:
        if self.n and t <= self.t[self.n - 1]:
            return   # out of order or repeated: keep time strictly increasing
        if self.n == self.size:
            for arr in (self.t, self.p, self.v, self.R, self.w):
                arr[:-1] = arr[1:]
            self.n -= 1
        i = self.n
        self.t[i], self.p[i], self.v[i], self.R[i], self.w[i] = t, p, v, R, w
        self.n += 1

    def lookup(self, ts: np.ndarray):
        """Extrapolate (p, v, R, w) to times ts from the newest state at or before each; mask of valid rows."""
        j = np.searchsorted(self.t[:self.n], ts, side="right") - 1
        ok = j >= 0
        j = np.maximum(j, 0)
        dt = (ts - self.t[j])[:, None]
        return self.p[j] + self.v[j] * dt, self.v[j], self.R[j], self.w[j], ok


class ContactPipeline:
    """Event-driven estimation: idle (bias and rest tracking) until the trigger fires, then the EKF.

    `process(batch)` takes an (n, 7) array of t, gyro xyz (rad/s), accel xyz
    (m/s^2) in the IMU frame and returns (events, estimate or None).
    """

    def __init__(self, detector: OnsetDetector, conditioner: GyroConditioner, ekf_params: EkfParams,
                 method: str = "ekf"):
        self.detector = detector
        self.cond = conditioner
        self.ekf = ContactEKF(ekf_params)
        self.method = method
        self.proprio = ProprioHistory()
        self.tracking = False
        self.onset_t: float | None = None
        self._t_prev: float | None = None
        self._wwT = np.zeros((3, 3))
        self._w_sum = np.zeros(3)
        self._t_out = -np.inf
        self.latest: ContactEstimate | None = None

    def add_proprio(self, t: float, p: np.ndarray, v: np.ndarray, R: np.ndarray, w: np.ndarray) -> None:
        self.proprio.add(t, p, v, R, w)

    def release(self) -> None:
        """End the contact episode: back to bias tracking and an armed trigger."""
        self.tracking = False
        self.onset_t = None
        self.cond.freeze_bias(False)
        self.detector.rearm()

    def process(self, batch: np.ndarray) -> tuple[list[dict], ContactEstimate | None]:
        events: list[dict] = []
        if len(batch) == 0:
            return events, None
        t, gyro, accel = batch[:, 0], batch[:, 1:4], batch[:, 4:7]
        start = 0
        if not self.tracking:
            hit = self.detector.process(t, accel)
            if hit < 0:
                self.cond.track_bias(t, gyro)
                self.cond.lowpass(gyro)      # keep the filter history warm
                return events, None
            self.cond.track_bias(t[:hit], gyro[:hit])
            p, v, _, _, ok = self.proprio.lookup(t[hit:hit + 1])
            if not ok[0]:
                self.detector.rearm()        # no proprioception yet: cannot start
                self.cond.lowpass(gyro)
                return events, None
            self.cond.freeze_bias(True)
            self.ekf.start(p[0], v[0])
            self.tracking = True
            self.onset_t = float(t[hit])
            self._t_prev = float(t[hit])
            self._wwT[:] = 0.0
            self._w_sum[:] = 0.0
            self._t_out = -np.inf
            start = hit
            events.append({"kind": "contact_onset", "t": self.onset_t, "p_tcp": p[0].tolist()})
        w_f = self.cond.lowpass(gyro)[start:]
        ts = t[start:]
        p, v, R, w_tcp, ok = self.proprio.lookup(ts)
        w_obj = self.cond.object_rate_world(w_f, R, w_tcp)
        ekf = self.ekf
        t_prev = self._t_prev
        for k in range(len(ts)):
            if not ok[k]:
                continue
            dt = ts[k] - t_prev
            if dt <= 0:
                dt = 1e-6
            ekf.step(dt, w_obj[k], p[k], v[k])
            t_prev = ts[k]
        self._t_prev = t_prev
        good = w_obj[ok]
        self._wwT += good.T @ good
        self._w_sum += good.sum(axis=0)
        estimate = None
        if ts[-1] - self._t_out >= OUTPUT_PERIOD_S:
            self._t_out = ts[-1]
            estimate = self._estimate(float(ts[-1]))
            self.latest = estimate
        return events, estimate

    def _axis(self) -> np.ndarray | None:
        vals, vecs = np.linalg.eigh(self._wwT)
        axis = vecs[:, -1]
        rms = np.sqrt(vals[-1] / max(self.ekf.steps, 1))
        if rms < MIN_AXIS_RATE_RAD_S:
            return None
        return axis if np.dot(axis, self._w_sum) >= 0 else -axis

    def _estimate(self, t: float) -> ContactEstimate:
        ekf = self.ekf
        axis = self._axis()
        Pc = ekf.P[6:9, 6:9]
        if axis is not None:
            proj = np.eye(3) - np.outer(axis, axis)
            in_plane = float(np.sqrt(max(np.linalg.eigvalsh(proj @ Pc @ proj)[-1], 0.0)))
        else:
            in_plane = float(np.sqrt(np.linalg.eigvalsh(Pc)[-1]))
        return ContactEstimate(t=t, onset_t=self.onset_t, p=ekf.p_c.copy(), std=ekf.std_c.copy(), axis=axis,
                               converged=in_plane < CONVERGED_STD_M and ekf.steps > 100, nis=ekf.nis,
                               steps=ekf.steps)
