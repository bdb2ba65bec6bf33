"""The estimators' compiled loops: numba functions that release the GIL and cache their machine code.

They are compiled when their module is imported, for the signatures given (any array layout), so no
call compiles mid-episode: the first import after an install takes about 30 s on a 2-core machine,
later ones about 2 s (the cache beside each file in `__pycache__`, or NUMBA_CACHE_DIR).
NUMBA_DISABLE_JIT=1 runs them as plain Python, for debugging.

- `linalg`: the small linear algebra (solves, products, a symmetric eigendecomposition, the
  collapsed update in Joseph form);
- `records`: the named records the `ekf` run keeps its state and parameters in;
- `model`: `ekf`'s measurement model, a block of samples to its information (A, b);
- `evidence`: the TCP positions as evidence (control.estimators.positions);
- `run`: the whole `ekf` run of a batch (blocks, the consistency window, the positions);
- `report`: `ekf`'s report, and the rate moments and rotation axes every output reports.
"""
from __future__ import annotations

# IEEE division (inf, nan) as in numpy, not Python's ZeroDivisionError; the GIL released meanwhile.
JIT = dict(nogil=True, error_model="numpy")
BUILDING = False        # set by `build` before it imports the kernel modules
EXPORTS: list = []      # (module, name, signature, function) of every kernel with a signature, when BUILDING


def jit(signature=None):
    """njit for `signature`, cached when numba finds a writable place for it (the source's
    __pycache__, NUMBA_CACHE_DIR, or the user's cache). In a read-only install with neither (a
    hardened service without NUMBA_CACHE_DIR) numba refuses to cache at all: compile each start.

    Without a signature (a helper only compiled functions call) it is compiled with its first
    caller, which has one and is compiled at import."""
    def wrap(fn):
        from numba import njit
        if BUILDING:                 # compiled ahead of time: for `build` to export, never cached
            if signature is None:
                return njit(**JIT)(fn)
            EXPORTS.append((fn.__module__.rsplit(".", 1)[-1], fn.__name__, signature, fn))
            return njit(signature, **JIT)(fn)
        args = () if signature is None else (signature,)
        try:
            return njit(*args, cache=True, **JIT)(fn)
        except RuntimeError as exc:
            if "cannot cache" not in str(exc):
                raise
            return njit(*args, cache=False, **JIT)(fn)
    return wrap
