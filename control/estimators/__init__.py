"""The contact estimators the pipeline can run, by name: one module per family in this package.

Each module defines `ESTIMATORS`, a tuple of `EstimatorSpec` (name, one-line summary, and how to
build the estimator from the pipeline's parameters and the plane of motion). The estimators derive
from `ContactEstimator`, whose hooks the pipeline calls on every estimator alike; an estimator
that has no use for one keeps the no-op. Adding an estimator is adding a module here (and its test).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from tecdard.control.plugins import new_modules


class Snapshot(NamedTuple):
    """What one output reports of an estimator: `report()` and the counters, as of one moment."""
    p: np.ndarray              # the contact, world, m
    cov: np.ndarray            # its reported 3 x 3 covariance, m^2
    stat: np.ndarray           # the estimator's own in-plane statistic (report's third)
    steps: int
    nis: float
    consistency: float | None


class ContactEstimator:
    """What the pipeline asks of an estimator. Every one implements `start` (at onset), `update`
    (a run of samples) and `report`; the hooks below default to nothing, and `advance` to `update`
    segment by segment."""

    method = "estimator"
    steps = 0              # samples used so far this episode
    nis = 0.0              # the latest normalised innovation squared (0: none)
    consistency = None     # smoothed NIS over its expectation (None: the estimator does not measure it)
    # True: update's w, p and w_tcp are aligned for the position evidence, each TCP position with the
    # twist read `fingertip_lag_s` after it (ContactPipeline.process_all). False: all as of the
    # sample's own time, as the paper takes them.
    lag_aligned_positions = False

    def start(self, p_g, v_g) -> None:
        """A contact episode begins with the TCP at p_g (m) moving at v_g (m/s), world."""
        raise NotImplementedError

    def update(self, dt, w, p, v, var_v=None, var_w=None, fresh=None, w_tcp=None, paired=None) -> None:
        """Samples: dt (s), the object's rate w (rad/s), the TCP's p (m) and v (m/s), world, per row.
        (`paired`, see ContactKF.update: what a held v pairs with; estimators may ignore it.)"""
        raise NotImplementedError

    def report(self):
        """(p_c world m, its 3 x 3 covariance m^2, the estimator's own in-plane statistic)."""
        raise NotImplementedError

    def snapshot(self) -> Snapshot:
        """The report and the counters as they stand now."""
        return Snapshot(*self.report(), self.steps, self.nis, self.consistency)

    def advance(self, ends, n_reports: int, dt, w, p, v, var_v, var_w, fresh, w_tcp=None,
                paired=None) -> list[Snapshot]:
        """`update` over the samples (update's arguments, the n rows of a batch) in segments that end
        at `ends` (increasing row indices, the last n); returns the snapshot after each of the first
        n_reports segments (the pipeline reports there). An estimator may run the segments in one
        go (ContactKF) as long as the snapshots are what segment-by-segment updates give."""
        snaps, k0 = [], 0
        for j, k1 in enumerate(ends):
            sl = slice(k0, k1)
            self.update(dt[sl], w[sl], p[sl], v[sl], var_v[sl], var_w[sl], fresh[sl],
                        None if w_tcp is None else w_tcp[sl], None if paired is None else tuple(a[sl] for a in paired))
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
    name: str                  # the `estimator.method` and `--method` value
    summary: str               # one line, for the CLI's help and the docs
    build: Callable            # (params: control.pipeline.PipelineParams, plane: Plane | None) -> ContactEstimator


REGISTRY: dict[str, EstimatorSpec] = {}
_discovered: set[str] = set()


def discover() -> dict[str, EstimatorSpec]:
    """Import every estimator module on this package's path (once each) and register its ESTIMATORS."""
    for module in new_modules(__path__, __name__, _discovered):
        for spec in getattr(module, "ESTIMATORS", ()):
            if spec.name in REGISTRY and REGISTRY[spec.name] is not spec:
                raise ValueError(f"estimator {spec.name!r} is defined twice")
            REGISTRY[spec.name] = spec
    return REGISTRY


def names() -> tuple[str, ...]:
    """The estimator names: `ekf` first (the default), then the rest in registration order."""
    found = discover()
    return tuple(sorted(found, key=lambda n: (n != "ekf", n != "paper-ekf")))


def build(method: str, params, plane) -> ContactEstimator:
    spec = discover().get(method)
    if spec is None:
        raise ValueError(f"method: unknown estimator {method!r} (known: {', '.join(names())})")
    return spec.build(params, plane)

