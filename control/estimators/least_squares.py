"""The paper's least-squares baselines: svd-geo, gd-geo, svd-diff, gd-diff (windowed, causal)."""
from tecdard.control.baselines import BASELINES, make_baseline
from tecdard.control.estimators import EstimatorSpec


def _spec(method: str) -> EstimatorSpec:
    solver, kind = method.split("-")
    what = "geometric (positions)" if kind == "geo" else "differential (velocities)"
    return EstimatorSpec(method, f"{what} least squares by {'SVD' if solver == 'svd' else 'gradient descent'}",
                         lambda params, plane: make_baseline(method, plane, params.baseline))


ESTIMATORS = tuple(_spec(m) for m in BASELINES)
