"""The paper's comparison baselines (`svd-geo`, `gd-geo`, `svd-diff`, `gd-diff`): SVD and gradient descent on
the geometric and differential constraints.

- geometric (`*-geo`): p(t) - c = R(t) (p(0) - c), R(t) integrated from the
  gyro since onset; least squares over the whole observation period.
- differential (`*-diff`): v = w x (p - c) at each instant; least squares over
  a short sliding window (`window_s`), with no state prior - which is why the
  paper finds them fast but oscillating.
Both solvers see the same normal equations: `svd-*` solves them by SVD
(minimum norm along unobservable directions, i.e. the TCP's coordinate at
onset along a line contact), `gd-*` runs warm-started gradient descent from
the previous estimate (a fixed number of iterations per update).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from tecdard.control.estimators.base import UNOBSERVED_STD_M, ContactEstimator, EstimatorSpec
from tecdard.control.geometry import Plane, cross_rows, rotvec_to_matrix
from tecdard.control.measurements import Samples
from tecdard.options import option, read_options

RANK_RTOL = 1e-6


@dataclass
class BaselineParams:
    """The `estimator.baseline` section, which the four share."""
    window_s: float = option(0.03, "the differential methods' sliding window", unit="s", above=0.0)
    gd_iterations: int = option(10, "gradient steps per update (gd-geo, gd-diff)", minval=1, maxval=1000)
    min_dof: int = 6             # residual degrees of freedom before a std is reported

    @classmethod
    def from_config(cls, section) -> "BaselineParams":
        return read_options(cls, section)


class _LeastSquares(ContactEstimator):
    """Shared machinery: normal equations around the onset TCP, SVD solve, residual-based covariance."""

    method = "baseline"

    def __init__(self, params: BaselineParams | None = None, plane: Plane | None = None, solver: str = "svd"):
        self.params = params or BaselineParams()
        self.plane = plane
        self.solver = solver
        self.d = 2 if plane is not None else 3
        self.origin = np.zeros(3)
        self.c = np.zeros(self.d)
        self.steps = 0
        self.rejected = 0
        self.nis = 0.0
        self._A = np.zeros((self.d, self.d))
        self._b = np.zeros(self.d)
        self._zz = 0.0
        self._m = 0

    def start(self, p_g: np.ndarray, v_g: np.ndarray) -> None:
        self.origin = np.asarray(p_g, dtype=float).copy()
        if self.plane is not None:
            self.plane.origin = self.origin
        self.c = np.zeros(self.d)
        self.steps = 0
        self._reset_sums()

    def _reset_sums(self) -> None:
        self._A[:] = 0.0
        self._b[:] = 0.0
        self._zz = 0.0
        self._m = 0

    def _solve(self) -> None:
        A, b = self._A, self._b
        if self._m == 0:
            return
        if self.solver == "svd":
            U, s, Vt = np.linalg.svd(A)
            keep = s > RANK_RTOL * max(s[0], 1e-300)
            self.c = Vt[keep].T @ ((U[:, keep].T @ b) / s[keep])
        else:
            lam_max = float(np.linalg.eigvalsh(A)[-1])
            if lam_max <= 0:
                return
            step = 1.0 / lam_max
            c = self.c
            for _ in range(self.params.gd_iterations):
                c = c - step * (A @ c - b)
            self.c = c

    def _cov(self) -> np.ndarray:
        A = self._A
        dof = self.d * self._m - self.d
        cov = np.full((self.d, self.d), 0.0)
        U, s, Vt = np.linalg.svd(A) if self._m else (np.eye(self.d), np.zeros(self.d), np.eye(self.d))
        keep = s > RANK_RTOL * max(s[0] if len(s) else 0.0, 1e-300)
        if dof >= self.params.min_dof and np.any(keep):
            rss = max(self._zz - 2 * self.c @ self._b + self.c @ A @ self.c, 0.0)
            sigma2 = rss / dof
            cov = Vt[keep].T @ np.diag(sigma2 / s[keep]) @ Vt[keep]
            unobs = Vt[~keep]
        else:
            unobs = np.eye(self.d)
        for u in unobs:
            cov = cov + UNOBSERVED_STD_M ** 2 * np.outer(u, u)
        return cov

    def covariance(self) -> np.ndarray:
        cov = self._cov()
        return self.plane.lift_cov(cov, UNOBSERVED_STD_M ** 2) if self.plane is not None else cov

    def report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p_c = self.plane.lift(self.c) if self.plane is not None else self.origin + self.c
        cov = self.covariance()
        return p_c, cov, cov


class DiffLeastSquares(_LeastSquares):
    """`svd-diff` / `gd-diff`: -[w]x c = v - w x (p - p0), over the last `window_s`."""

    def __init__(self, params=None, plane=None, solver="svd"):
        super().__init__(params, plane, solver)
        self.method = f"{solver}-diff"
        self._blocks: collections.deque = collections.deque()
        self._t = 0.0

    def start(self, p_g, v_g) -> None:
        super().start(p_g, v_g)
        self._blocks.clear()
        self._t = 0.0

    def update(self, samples: Samples) -> None:
        """dt, w, p and v of each sample (the rest of the record is unused)."""
        dt, w, p, v = samples.dt, samples.w, samples.p, samples.v
        if len(dt) == 0:
            return
        if self.plane is not None:
            w_n = w @ self.plane.n
            r0 = self.plane.point2(p)
            z = self.plane.vec2(v) - w_n[:, None] * (r0 @ Plane.J.T)
            # H = -w_n J, H^T H = w_n^2 I, H^T z = -w_n J^T z
            A = np.sum(w_n ** 2) * np.eye(2)
            b = -(w_n[:, None] * (z @ Plane.J)).sum(axis=0)
        else:
            r0 = p - self.origin
            z = v - cross_rows(w, r0)
            ww = (w * w).sum(axis=1)
            A = ww.sum() * np.eye(3) - w.T @ w            # sum [w]x^T [w]x
            b = cross_rows(w, z).sum(axis=0)              # sum (-[w]x)^T z = sum w x z
        self._t += float(np.sum(dt))
        self._blocks.append((self._t, A, b, float((z * z).sum()), len(dt)))
        while self._blocks and self._blocks[0][0] < self._t - self.params.window_s:
            self._blocks.popleft()
        self._reset_sums()
        for _, A_k, b_k, zz_k, m_k in self._blocks:
            self._A += A_k
            self._b += b_k
            self._zz += zz_k
            self._m += m_k
        self._solve()
        self.steps += len(dt)


class GeoLeastSquares(_LeastSquares):
    """`svd-geo` / `gd-geo`: (I - R(t)) c = p(t) - p0 with R(t) integrated since onset, all samples since onset."""

    def __init__(self, params=None, plane=None, solver="svd"):
        super().__init__(params, plane, solver)
        self.method = f"{solver}-geo"
        self._R = np.eye(self.d)
        self._theta = 0.0

    def start(self, p_g, v_g) -> None:
        super().start(p_g, v_g)
        self._R = np.eye(self.d)
        self._theta = 0.0

    def update(self, samples: Samples) -> None:
        """One geometric residual per update (per block), rotation integrated over the block's samples."""
        dt, w, p = samples.dt, samples.w, samples.p
        if len(dt) == 0:
            return
        if self.plane is not None:
            self._theta += float((w @ self.plane.n) @ dt)
            c, s = np.cos(self._theta), np.sin(self._theta)
            self._R = np.array([[c, -s], [s, c]])
            r = self.plane.point2(p[-1])
        else:
            self._R = rotvec_to_matrix((w * dt[:, None]).sum(axis=0)) @ self._R
            r = p[-1] - self.origin
        M = np.eye(self.d) - self._R
        self._A += M.T @ M
        self._b += M.T @ r
        self._zz += float(r @ r)
        self._m += 1
        self._solve()
        self.steps += len(dt)


def make_baseline(method: str, plane: Plane | None = None, params: BaselineParams | None = None):
    solver, kind = method.split("-")
    cls = GeoLeastSquares if kind == "geo" else DiffLeastSquares
    return cls(params, plane, solver)


BASELINES = ("svd-geo", "gd-geo", "svd-diff", "gd-diff")


def _spec(method: str) -> EstimatorSpec:
    solver, kind = method.split("-")
    what = "geometric (positions)" if kind == "geo" else "differential (velocities)"
    return EstimatorSpec(method, f"{what} least squares by {'SVD' if solver == 'svd' else 'gradient descent'}",
                         lambda options, plane: make_baseline(method, plane, options), "baseline", BaselineParams)


ESTIMATORS = tuple(_spec(m) for m in BASELINES)
