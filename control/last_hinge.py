"""The hinge the last rotate turned about, kept to give the next rotate its probe direction.

A rotate's first phase probes along `direction` and the fingertip's turn tells the estimator the hinge.
The probe must run along the handle's tangent at the grasp. After a rotate the handle has turned, and
the configured default (straight up) no longer runs along it: a second rotate with it failed 3 times
in 3 ("estimator innovations 11x"). Where the daemon knows the hinge it last turned about, and the TCP
still lies on that hinge's circle (the object is held where the rotate left it), the next rotate
without a `direction` probes along the tangent there, onwards in the same sense, and says so.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The TCP still lies on the hinge's circle: its distance from the axis within this of the rotate's radius
# (the arc's own tracking error is a few mm; a task or a person that moved the arm moves it further).
ON_CIRCLE_M = 0.010
MIN_RADIUS_M = 0.01        # a rotate refuses an arc closer than this to its hinge (control/rotate.py)


@dataclass(frozen=True)
class LastHinge:
    task: str               # the rotate that found it
    p: np.ndarray           # a point on the axis, world, m
    axis: np.ndarray        # unit, world, oriented so that axis x (p_tcp - p) is the way the rotate turned
    radius: float           # the TCP's distance from the axis, m, as the rotate ended

    @classmethod
    def from_result(cls, task: str, result: dict) -> LastHinge | None:
        """The hinge of a rotate's `task_done` result, or None where it has none usable."""
        try:
            hinge = result["hinge"]
            p, axis, radius = (np.asarray(hinge["p"], float), np.asarray(hinge["axis"], float),
                               float(result["radius"]))
        except (KeyError, TypeError, ValueError):
            return None
        norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else 0.0
        if p.shape != (3,) or not np.all(np.isfinite(p)) or not np.isfinite(norm) or norm < 0.5 \
                or not np.isfinite(radius) or radius < MIN_RADIUS_M:
            return None
        return cls(task, p, axis / norm, radius)

    def tangent(self, p_tcp: np.ndarray) -> tuple[np.ndarray | None, str]:
        """The unit tangent of the hinge's circle at `p_tcp` (onwards, the way the rotate turned), or None
        and why not."""
        r = np.asarray(p_tcp, float) - self.p
        r_perp = r - float(r @ self.axis) * self.axis
        rho = float(np.linalg.norm(r_perp))
        if abs(rho - self.radius) > ON_CIRCLE_M or rho < MIN_RADIUS_M:
            return None, (f"the TCP is {rho * 1e3:.0f} mm from the hinge of {self.task}, which it left at "
                          f"{self.radius * 1e3:.0f} mm: the object is no longer held on that hinge's circle")
        t = np.cross(self.axis, r_perp) / rho
        return t, f"the tangent at the grasp about the hinge {self.task} found"
