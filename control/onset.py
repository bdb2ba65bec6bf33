"""Contact-onset trigger: accelerometer deviation from its tracked rest level, over sample batches."""
from __future__ import annotations

import math

import numpy as np


class OnsetDetector:
    """Fires when |accel - rest| exceeds `accel_threshold` (m/s^2).

    The rest level (gravity plus any steady offset, sensor frame) is tracked while
    armed with time constant `rest_tau_s`; the detector arms only after `warmup_s`
    of samples so the rest level is known. After firing it stays disarmed until
    `rearm()`, which is the estimator's call once a contact episode ends.
    """

    def __init__(self, accel_threshold: float = 0.4, rest_tau_s: float = 0.5, warmup_s: float = 0.1):
        if accel_threshold <= 0:
            raise ValueError("accel_threshold: must be > 0 m/s^2")
        self.accel_threshold = accel_threshold
        self.rest_tau_s = rest_tau_s
        self.warmup_s = warmup_s
        self.rest = None            # (3,) rest level, sensor frame, m/s^2
        self._seen_s = 0.0
        self.armed = True

    @classmethod
    def from_config(cls, section) -> "OnsetDetector":
        return cls(
            accel_threshold=section.getfloat("accel_threshold", 0.4, above=0.0),
            rest_tau_s=section.getfloat("rest_tau_s", 0.5, above=0.0),
            warmup_s=section.getfloat("warmup_s", 0.1, minval=0.0),
        )

    def rearm(self) -> None:
        """Start looking for the next onset; the rest level keeps its last value."""
        self.armed = True

    def process(self, t: np.ndarray, accel: np.ndarray) -> int:
        """Index into the batch of the first sample past the threshold, or -1."""
        n = len(t)
        if n == 0:
            return -1
        if self.rest is None:
            self.rest = accel.mean(axis=0)
        hit = -1
        if self.armed and self._seen_s >= self.warmup_s:
            dev = accel - self.rest
            over = np.flatnonzero(np.einsum("ij,ij->i", dev, dev) > self.accel_threshold**2)
            if len(over):
                hit = int(over[0])
                self.armed = False
        if hit < 0:
            # Track the rest level only on batches that contain no onset.
            dt = float(t[-1] - t[0]) if n > 1 else 0.0
            alpha = 1.0 - math.exp(-(dt + 1e-4) / self.rest_tau_s)
            self.rest = self.rest + alpha * (accel.mean(axis=0) - self.rest)
            self._seen_s += dt
        return hit
