"""What the contact pipeline asks of an estimator (`ContactEstimator`), how one is registered
(`EstimatorSpec`) and what one output reports of it (`Snapshot`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from tecdard.control.measurements import Samples

UNOBSERVED_STD_M = 0.5     # one-sigma reported along an unobservable direction
CONSISTENCY_TAU_S = 0.05   # smoothing of an estimator's NIS ratio (innovation consistency), s


class Snapshot(NamedTuple):
    """What one output reports of an estimator: `report()` and the counters, as of one moment."""
    p: np.ndarray              # the contact, world, m
    cov: np.ndarray            # its reported 3 x 3 covariance, m^2
    stat: np.ndarray           # the estimator's own in-plane statistic (report's third)
    steps: int
    nis: float
    consistency: float | None


class ContactEstimator:
    """What the pipeline asks of an estimator. Every one implements `start` (at onset), `update` (a
    run of samples, control.measurements.Samples) and `report`; the hooks below default to nothing,
    and `advance` to `update` segment by segment."""

    method = "estimator"
    steps = 0              # samples used so far this episode
    nis = 0.0              # the latest normalised innovation squared (0: none)
    consistency = None     # smoothed NIS over its expectation (None: the estimator does not measure it)

    def start(self, p_g, v_g) -> None:
        """A contact episode begins with the TCP at p_g (m) moving at v_g (m/s), world."""
        raise NotImplementedError

    def update(self, samples: Samples) -> None:
        """A run of samples, in time order: use what the estimator needs of the record."""
        raise NotImplementedError

    def report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_c world m, its 3 x 3 covariance m^2, the estimator's own in-plane statistic)."""
        raise NotImplementedError

    def snapshot(self) -> Snapshot:
        """The report and the counters as they stand now."""
        return Snapshot(*self.report(), self.steps, self.nis, self.consistency)

    def advance(self, samples: Samples, ends, n_reports: int) -> list[Snapshot]:
        """`update` over the samples in segments that end at `ends` (increasing row indices, the last
        len(samples)); returns the snapshot after each of the first n_reports segments (the pipeline
        reports there). An estimator may run the segments in one go (ContactKF) as long as the
        snapshots are what segment-by-segment updates give."""
        snaps, k0 = [], 0
        for j, k1 in enumerate(ends):
            self.update(samples[k0:k1])
            if j < n_reports:
                snaps.append(self.snapshot())
            k0 = k1
        return snaps

    def set_arc_radial_var(self, var_m2_s2: float) -> None:
        """The controller follows an arc about the estimate: distrust the TCP velocity along the
        lever arm by this variance ((m/s)^2; 0 when not following)."""

    def set_eta_prior(self, mean: float, rel_std: float) -> None:
        """Eta's prior for the next episode: the scheduled value's error factor and its relative one-sigma."""

    def set_correlation(self, samples: float) -> None:
        """IMU samples that share one proprioception sample (their velocity errors are one error)."""

    def set_position_noise(self, sigma_m: float) -> None:
        """The TCP position's noise for the next episode, m (the configured value, or more when the
        proprioception shows more: ProprioTrack.sigma_p_effective)."""


@dataclass(frozen=True)
class EstimatorSpec:
    """One estimator by name. Its options are its own config section, `estimator.<section>`: `options`
    is their class, whose defaults make it and whose `from_config(section)` reads the section with the
    typed getters (None: no options); estimators of one family may share a section. `build(options,
    plane)` makes the estimator: options as read (or the defaults), plane the control.geometry.Plane
    of motion or None (3D)."""
    name: str                  # the `estimator.method` and `--method` value
    summary: str               # one line, for the CLI's help and the docs
    build: Callable            # (options, plane) -> ContactEstimator
    section: str | None = None       # its options' section under `estimator`
    options: type | None = None      # its options' class: defaults, and from_config(section)
