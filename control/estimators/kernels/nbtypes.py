"""numba's types of the `records`: what the kernels' signatures name (imported only where numba compiles)."""
from __future__ import annotations

from numba import from_dtype, types

from tecdard.control.estimators.kernels.records import (EVIDENCE_STATUS, RUN_PARAMS, STATUS, EkfState, Evidence,
                                                        Frame, Outputs, Samples, Window)

_V, _M = types.float64[::1], types.float64[:, ::1]
STATUS_T = from_dtype(STATUS)[::1]
PARAMS_T = from_dtype(RUN_PARAMS)[::1]
WINDOW_T = types.NamedTuple((_V, _M, _M, _V), Window)
EVIDENCE_T = types.NamedTuple((from_dtype(EVIDENCE_STATUS)[::1], _V, _V, _V, _M, _M, _V, _V, _M, _V), Evidence)
SAMPLES_T = types.NamedTuple((_V, _M, _M, _M, _M, _M, _M, _M, _V, _V, types.boolean[::1]), Samples)
FRAME_T = types.NamedTuple((_M, _V, _V), Frame)
STATE_T = types.NamedTuple((_V, _M, STATUS_T, _V, WINDOW_T, EVIDENCE_T), EkfState)
OUTPUTS_T = types.NamedTuple((_M, types.float64[:, :, ::1], _M, _M), Outputs)
