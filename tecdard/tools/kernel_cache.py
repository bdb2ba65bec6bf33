"""The estimator's compiled kernels (control/estimators/kernels/, numba) and their on-disk cache.

Importing them compiles each kernel for its signature, or loads it from numba's cache:
60-90 s of compiling on a 2-core machine against about 1.5 s of loading. `make install`
warms the cache (`tecdard warm`); where a start still has to compile (a wheel install, a service
with an empty NUMBA_CACHE_DIR), the daemon says so in one line before it does. `tecdard doctor`
reports the state.

The cache is found the way numba finds it (its locator classes in order: NUMBA_CACHE_DIR, the
source's __pycache__, the user-wide cache), and an entry counts only if numba would load it: the
same numba version and the same source stamp (the file's mtime and size) as the source now.
"""
from __future__ import annotations

import glob
import importlib.util
import os
import pickle
import time
from dataclasses import dataclass

KERNELS_PACKAGE = "tecdard.control.estimators.kernels"
KERNEL_MODULES = ("linalg", "report", "model", "evidence", "run")     # each holds compiled functions
COLD_COMPILE_S = 90.0          # s, what a cold compile is said to take on 2 cores (benchmarks/startup.md)


@dataclass(frozen=True)
class CacheState:
    warm: bool
    path: str | None            # where numba caches them (None: nowhere writable)
    fresh: int                  # kernels with a loadable cache entry
    expected: int               # kernels in the module
    source: str

    def describe(self) -> str:
        if self.path is None:
            return (f"numba finds no writable cache for {self.source}: every start compiles the estimator "
                    f"(about {COLD_COMPILE_S:.0f} s); set NUMBA_CACHE_DIR to a writable directory")
        if self.warm:
            return f"compiled estimator kernels cached in {self.path} ({self.fresh} of {self.expected})"
        return (f"compiled estimator kernels not cached in {self.path} ({self.fresh} of {self.expected} "
                f"fresh): this start compiles them, about {COLD_COMPILE_S:.0f} s on 2 cores; "
                "`tecdard warm` (make install) does it ahead")


def _sources() -> list[str]:
    out = []
    for name in KERNEL_MODULES:
        spec = importlib.util.find_spec(f"{KERNELS_PACKAGE}.{name}")
        if spec is None or spec.origin is None:
            raise RuntimeError(f"{KERNELS_PACKAGE}.{name} not found")
        out.append(spec.origin)
    return out


def _expected(source: str) -> int:
    with open(source, encoding="utf-8") as f:
        return sum(1 for line in f if line.startswith("@jit("))


def _locator(source: str):
    """numba's cache locator for functions of `source`, as numba picks it (None: nowhere writable)."""
    from numba.core import caching

    def probe():          # numba's locators read only the line number of the function
        pass

    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")     # renamed in numba 0.59
    for cls in impl._locator_classes:
        try:
            locator = cls.from_function(probe, source)
        except Exception:           # a locator that does not apply (IPython, zip) may raise
            locator = None
        if locator is not None:
            return locator
    return None


def _fresh(source: str, locator) -> int:
    """Cache entries of `source` that numba would load: its version, and the source's stamp now."""
    import numba
    path, stamp = locator.get_cache_path(), locator.get_source_stamp()
    base = os.path.splitext(os.path.basename(source))[0]
    fresh = 0
    for index in glob.glob(os.path.join(glob.escape(path), f"{base}.*.nbi")):
        try:
            with open(index, "rb") as f:
                version = pickle.load(f)
                if version != numba.__version__:
                    continue
                entry_stamp, overloads = pickle.loads(f.read())
        except Exception:
            continue
        if entry_stamp == stamp and overloads:
            fresh += 1
    return fresh


def state() -> CacheState:
    """Whether importing the kernels would load every one from numba's cache."""
    sources = _sources()
    expected = sum(_expected(s) for s in sources)
    fresh, path = 0, None
    for source in sources:
        locator = _locator(source)
        if locator is None:
            return CacheState(False, None, 0, expected, os.path.dirname(source))
        path = locator.get_cache_path()
        fresh += _fresh(source, locator)
    return CacheState(fresh >= expected > 0, path, fresh, expected, os.path.dirname(sources[0]))


def warm() -> tuple[CacheState, float]:
    """Compile (or load) every kernel now, which caches them; returns the state after and the seconds."""
    t0 = time.monotonic()
    for name in KERNEL_MODULES:
        importlib.import_module(f"{KERNELS_PACKAGE}.{name}")
    return state(), time.monotonic() - t0


def add_parser(sub) -> None:
    p = sub.add_parser("warm", help="compile the estimator's kernels into numba's cache (make install does)")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard warm`: compile (or load) the kernels now; an uncachable install still runs (each start
    compiles), which is said, not an install failure."""
    before = state()
    if not before.warm:
        print(f"compiling the estimator's kernels into {before.path} (about {COLD_COMPILE_S:.0f} s on 2 cores) ...",
              flush=True)
    after, took = warm()
    print(f"{after.describe()}; {'loaded' if before.warm else 'compiled'} in {took:.1f} s")
    return 0


def announce_compile() -> None:
    """One log line before a start that must compile the estimator's kernels."""
    import logging
    try:
        cache = state()
    except Exception as exc:         # the check must never stop a start
        logging.getLogger("tecdar").debug("kernel cache check failed: %s", exc)
        return
    if not cache.warm:
        logging.getLogger("tecdar").warning("%s", cache.describe())
