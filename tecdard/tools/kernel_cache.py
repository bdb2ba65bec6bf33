"""The estimator's compiled kernels (control/estimators/kernels/): built ahead of time, or numba's JIT cache.

`tecdard warm` (make install) compiles them ahead of time into an extension module beside their
sources (kernels.build): a start then loads it and imports no numba at all. Where that build is
missing or is not the sources' (a kernel edited since, no C compiler), importing the kernels
compiles each for its signature with numba's JIT, or loads it from numba's cache: 40-90 s of
compiling on a 2-core machine against about 1.5 s of loading. `tecdard warm` then warms that
cache instead; where a start still has to compile, the daemon says so in one line before it
does. `tecdard doctor` reports the state.

The JIT's cache is found the way numba finds it (its locator classes in order: NUMBA_CACHE_DIR, the
source's __pycache__, the user-wide cache), and an entry counts only if numba would load it: the
same numba version and the same source stamp (the file's mtime and size) as the source now.
"""
from __future__ import annotations

import glob
import importlib.util
import os
import pickle
import subprocess
import sys
import time
from dataclasses import dataclass

KERNELS_PACKAGE = "tecdard.control.estimators.kernels"
KERNEL_MODULES = ("linalg", "report", "model", "evidence", "run")     # each holds compiled functions
COLD_COMPILE_S = 90.0          # s, what a cold compile is said to take on 2 cores (benchmarks/startup.md)


@dataclass(frozen=True)
class CacheState:
    warm: bool
    path: str | None            # where numba caches them (None: nowhere writable); the built module when aot
    fresh: int                  # kernels with a loadable cache entry
    expected: int               # kernels in the module
    source: str
    aot: bool = False           # built ahead of time and current: nothing compiles, numba is not imported
    why_not_aot: str = ""

    def describe(self) -> str:
        if self.aot:
            return f"estimator kernels compiled ahead of time ({self.path}): nothing compiles at start"
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
    """Whether a start loads the kernels built ahead of time, or else every one from numba's cache."""
    from tecdard.control.estimators.kernels import build
    why = "TECDAR_KERNELS=jit" if os.environ.get("TECDAR_KERNELS") == "jit" else build.aot_problem()
    if why is None:
        spec = importlib.util.find_spec(f"{KERNELS_PACKAGE}.{build.MODULE}")
        n = sum(len(names) for names in build.PUBLIC.values())
        return CacheState(True, spec.origin, n, n, build.HERE, aot=True)
    jit = jit_state()
    return CacheState(jit.warm, jit.path, jit.fresh, jit.expected, jit.source, why_not_aot=why)


def jit_state() -> CacheState:
    """Whether importing the kernels' modules would load every one from numba's cache."""
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


def warm_jit() -> tuple[CacheState, float]:
    """Compile (or load) every kernel with numba's JIT now, which caches them; the state after and the seconds."""
    t0 = time.monotonic()
    for name in KERNEL_MODULES:
        importlib.import_module(f"{KERNELS_PACKAGE}.{name}")
    return jit_state(), time.monotonic() - t0


def build_aot() -> str | None:
    """Build the kernels ahead of time in a process of its own (the JIT's cache can warm beside it on
    the second core); None when built, else why not (one line)."""
    proc = subprocess.run([sys.executable, "-m", f"{KERNELS_PACKAGE}.build"], capture_output=True, text=True)
    if proc.returncode == 0:
        return None
    lines = [line for line in (proc.stderr or proc.stdout).strip().splitlines() if line.strip()]
    return lines[-1] if lines else f"exit status {proc.returncode}"


def add_parser(sub) -> None:
    p = sub.add_parser("warm", help="compile the estimator's kernels ahead of time (make install does), "
                                    "or into numba's cache where that cannot be done")
    p.add_argument("--jit", action="store_true",
                   help="also fill numba's cache, for what imports the kernels' modules themselves (the tests)")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard warm`: build the kernels ahead of time; where that fails (no C compiler), compile (or
    load) them into numba's cache instead. An uncachable install still runs (each start compiles),
    which is said, not an install failure."""
    from tecdard.control.estimators.kernels import build
    with_jit = bool(getattr(args, "jit", False))
    t0 = time.monotonic()
    stale = build.aot_problem()
    jit_before = jit_state() if with_jit else None
    jit_proc = None
    if with_jit and stale is not None:     # two cores: the JIT's cache warms while the build runs
        jit_proc = subprocess.Popen([sys.executable, "-m", "tecdard.tools.kernel_cache"])
    problem = build_aot() if stale is not None else None
    if stale is not None:
        if problem is None:
            print(f"compiled the estimator's kernels ahead of time in {time.monotonic() - t0:.1f} s")
        else:
            print(f"the kernels could not be built ahead of time ({problem}): numba's JIT runs them", flush=True)
    if jit_proc is not None:
        jit_proc.wait()
    if (with_jit and jit_proc is None) or problem is not None:
        _warm_jit_and_say(jit_before or jit_state())
    print(state().describe())
    return 0


def _warm_jit_and_say(before: CacheState) -> None:
    if not before.warm:
        print(f"compiling the estimator's kernels into {before.path} (about {COLD_COMPILE_S:.0f} s on 2 cores) ...",
              flush=True)
    after, took = warm_jit()
    print(f"{after.describe()}; {'loaded' if before.warm else 'compiled'} in {took:.1f} s")


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
    elif not cache.aot:
        logging.getLogger("tecdar").info("the estimator's kernels run on numba's JIT: the ahead-of-time build is %s",
                                         cache.why_not_aot)


if __name__ == "__main__":        # `tecdard warm --jit` runs this beside the ahead-of-time build
    _warm_jit_and_say(jit_state())
