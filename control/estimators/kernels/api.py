"""The kernels as the estimators call them: the ahead-of-time build where it is current, else numba's JIT.

`build` compiles the kernels the estimators call, with all they call, into the extension `_compiled`
(`tecdard warm`, `make install`). It is loaded when its digest (`_compiled.digest`) is still that of the kernels' sources: then numba, LLVM
and the JIT's cache are never imported or read, and nothing is compiled at start. Otherwise (a
kernel edited since, an install that could not build it, or TECDAR_KERNELS=jit) the same
sources are compiled by numba's JIT at import, or loaded from its cache. Both are the same
compiler's machine code for the same signatures: their answers agree to the last digit
(tests/test_kernels_aot.py).
"""
from __future__ import annotations

import importlib
import os

from tecdard.control.estimators.kernels import build
from tecdard.control.estimators.kernels.constants import ETA_BLEND_SIGMA, ETA_PRIOR_LIMIT, GATE_HPH_RATIO, K_MIN

MODE_ENV = "TECDAR_KERNELS"       # "jit": numba's JIT whatever is built; "aot": the build or an error
__all__ = ["ETA_BLEND_SIGMA", "ETA_PRIOR_LIMIT", "GATE_HPH_RATIO", "K_MIN", "KIND", "WHY", "block_update", "output_ends",
           "ekf_advance", "ekf_segments", "eta_evidence", "eta_weight", "plane_rotation", "position_increment",
           "position_reset", "position_residual", "position_sums", "rate_moments", "report_state", "report_states",
           "rotation_axes", "segment_moments"]


class KernelsUnavailable(ImportError):
    """The kernels can be neither loaded from the build nor compiled here (one line)."""


def _load():
    """(functions by name, "aot" | "jit", why the JIT where it is)."""
    mode = os.environ.get(MODE_ENV, "auto")
    why = "TECDAR_KERNELS=jit" if mode == "jit" else build.aot_problem()
    if why is None:
        ext = importlib.import_module(f"{__package__}.{build.MODULE}")
        return {name: getattr(ext, build.export_name(module, name))
                for module, names in build.PUBLIC.items() for name in names}, "aot", None
    if mode == "aot":
        raise KernelsUnavailable(f"{MODE_ENV}=aot, but the ahead-of-time kernels are {why}")
    if build.write_execute_denied():
        raise KernelsUnavailable(
            f"the estimator's kernels are not built ahead of time ({why}) and this process may not create "
            "executable memory (MemoryDenyWriteExecute), which numba's JIT needs: run `sudo tecdard warm` in the "
            "install, or drop MemoryDenyWriteExecute from the unit")
    out = {}
    for module, names in build.PUBLIC.items():
        mod = importlib.import_module(f"{__package__}.{module}")
        out.update({name: getattr(mod, name) for name in names})
    return out, "jit", why


_FUNCTIONS, KIND, WHY = _load()
ekf_advance = _FUNCTIONS["ekf_advance"]
ekf_segments = _FUNCTIONS["ekf_segments"]
eta_evidence = _FUNCTIONS["eta_evidence"]
eta_weight = _FUNCTIONS["eta_weight"]
report_state = _FUNCTIONS["report_state"]
report_states = _FUNCTIONS["report_states"]
plane_rotation = _FUNCTIONS["plane_rotation"]
rate_moments = _FUNCTIONS["rate_moments"]
rotation_axes = _FUNCTIONS["rotation_axes"]
position_increment = _FUNCTIONS["position_increment"]
position_reset = _FUNCTIONS["position_reset"]
position_residual = _FUNCTIONS["position_residual"]
position_sums = _FUNCTIONS["position_sums"]
block_update = _FUNCTIONS["block_update"]
output_ends = _FUNCTIONS["output_ends"]
segment_moments = _FUNCTIONS["segment_moments"]
