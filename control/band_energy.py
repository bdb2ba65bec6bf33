"""The onset trigger's band-energy condition: the accelerometer's energy in a band, per sample, causally,
and how that band fits an IMU's rate (control.onset)."""
from __future__ import annotations

import math

import numpy as np


class SlidingBandEnergy:
    """Mean-square of the signal in [lo_hz, hi_hz] over a sliding window, per sample, causally.

    A sliding DFT of N = odr/lo_hz samples (bin spacing lo_hz) keeps the bins
    lo..hi; by Parseval their power is the band's mean square, summed over
    the 3 axes (units (m/s^2)^2). Recomputed from the last N-1 samples each
    batch, so it never accumulates rounding.
    """

    def __init__(self, odr_hz: float, lo_hz: float = 40.0, hi_hz: float = 200.0):
        if not 0 < lo_hz < hi_hz < odr_hz / 2:
            raise ValueError("band_hz: expected 0 < lo < hi < odr/2")
        self.N = int(round(odr_hz / lo_hz))
        k_lo = max(1, int(math.ceil(lo_hz * self.N / odr_hz - 1e-9)))
        k_hi = int(math.floor(hi_hz * self.N / odr_hz + 1e-9))
        self.k = np.arange(k_lo, k_hi + 1)
        self._hist = np.zeros((0, 3))
        self._index = 0          # absolute index of the first history sample

    def process(self, x: np.ndarray) -> np.ndarray:
        N = self.N
        ext = np.vstack([self._hist, x])
        m = self._index + np.arange(len(ext))
        phase = np.exp(-2j * np.pi * np.outer(m % N, self.k) / N)       # (L, K)
        # cumulative sums of x * e^{-j phi} per axis and bin, with a leading zero row
        C = np.zeros((len(ext) + 1, 3, len(self.k)), dtype=complex)
        C[1:] = np.cumsum(ext[:, :, None] * phase[:, None, :], axis=0)
        ends = np.arange(len(self._hist) + 1, len(ext) + 1)
        starts = np.maximum(ends - N, 0)
        S = C[ends] - C[starts]
        energy = 2.0 / (N * N) * np.sum(np.abs(S) ** 2, axis=(1, 2))
        energy[ends - starts < N] = 0.0      # not a full window yet
        keep = min(N - 1, len(ext))
        self._index += len(ext) - keep
        self._hist = ext[len(ext) - keep:].copy()
        return energy


BAND_TOP_OF_NYQUIST = 0.9    # a band's upper edge is lowered to this fraction of half the IMU's rate at most
BAND_MIN_OCTAVES = 0.5        # ... keeping at least this much band above its lower edge, else the condition is off


def band_at_rate(band_hz: tuple, odr_hz: float) -> tuple[SlidingBandEnergy | None, str | None]:
    """The band-energy condition at an IMU's rate: (its window, or None when it cannot run; what was
    changed or why it is off, in one line, or None). A band whose upper edge lies at or above half the
    rate is lowered to BAND_TOP_OF_NYQUIST of it while the band keeps BAND_MIN_OCTAVES above its lower
    edge (a 200-400 Hz IMU on a tool); below that the condition is off and the others run."""
    lo, hi = float(band_hz[0]), float(band_hz[1])
    nyquist = odr_hz / 2.0
    if hi < nyquist:
        return SlidingBandEnergy(odr_hz, lo, hi), None
    top = BAND_TOP_OF_NYQUIST * nyquist
    if top >= lo * 2.0 ** BAND_MIN_OCTAVES:
        return SlidingBandEnergy(odr_hz, lo, top), (
            f"onset band {lo:g}-{hi:g} Hz reaches half the IMU's rate of {odr_hz:.4g} Hz: the band-energy "
            f"condition runs on {lo:g}-{top:.4g} Hz")
    return None, (f"onset band {lo:g}-{hi:g} Hz does not fit under half the IMU's rate of {odr_hz:.4g} Hz: the "
                  "band-energy condition is off, the others run")
