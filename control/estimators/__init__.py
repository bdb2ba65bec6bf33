"""The contact estimators, by name: each module of this package registers its own.

A module that defines `ESTIMATORS`, a tuple of `base.EstimatorSpec`, adds them: the estimator
derives from `base.ContactEstimator` and takes `control.measurements.Samples`; its options are its
own section of the config's `estimator`. Adding an estimator is adding its module (and its test);
nothing else names the estimators. `base` holds the interface, `kernels` the compiled loops.
"""
from __future__ import annotations

from tecdard.control.estimators.base import ContactEstimator, EstimatorSpec
from tecdard.control.plugins import new_modules

DEFAULT = "ekf"
REGISTRY: dict[str, EstimatorSpec] = {}
_discovered: set[str] = set()


def discover() -> dict[str, EstimatorSpec]:
    """Import every module on this package's path (once each) and register its ESTIMATORS."""
    for module in new_modules(__path__, __name__, _discovered):
        for spec in getattr(module, "ESTIMATORS", ()):
            if spec.name in REGISTRY and REGISTRY[spec.name] is not spec:
                raise ValueError(f"estimator {spec.name!r} is defined twice")
            REGISTRY[spec.name] = spec
    return REGISTRY


def names() -> tuple[str, ...]:
    """The estimator names: `ekf` first (the default), `paper-ekf` next, then the rest in registration order."""
    found = discover()
    return tuple(sorted(found, key=lambda n: (n != DEFAULT, n != "paper-ekf")))


def read_options(section) -> dict[str, object]:
    """Every registered estimator's options from its section of `estimator` (each section once, read
    whichever method runs, so a typo in any of them is an error): section name -> options."""
    out: dict[str, object] = {}
    for spec in discover().values():
        if spec.section is not None and spec.section not in out:
            out[spec.section] = spec.options.from_config(section.section(spec.section))
    return out


def options_of(method: str, options: dict) -> object:
    """The options `method` is built with: its section's as read, or its defaults (an empty section)."""
    spec = _spec(method)
    if spec.section is None:
        return None
    if spec.section not in options:
        options[spec.section] = spec.options()
    return options[spec.section]


def build(method: str, options: dict, plane) -> ContactEstimator:
    """The estimator `method` with its options (read_options' dict; sections not in it get defaults)."""
    return _spec(method).build(options_of(method, options), plane)


def _spec(method: str) -> EstimatorSpec:
    spec = discover().get(method)
    if spec is None:
        raise ValueError(f"method: unknown estimator {method!r} (known: {', '.join(names())})")
    return spec
