"""The `ekf` run's named records: its state and parameters (numpy only; `nbtypes` gives numba's view of them).

Scalars that change together live in numpy structured arrays of one element (numba reads and
writes their fields by name: `status[0].steps`); arrays that belong together live in named tuples
of C-contiguous arrays. The compiled functions take these records, never long lists of scalars.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

STATUS = np.dtype([
    ("steps", np.int64),           # IMU samples taken this episode
    ("rejected", np.int64),        # samples the NIS gate rejected
    ("nis", np.float64),           # the last gated sample's NIS
    ("consistency", np.float64),   # the smoothed window NIS over its expectation
    ("win_blocks", np.int64),      # the open consistency window: its blocks,
    ("win_t", np.float64),         # its duration (s),
    ("win_samples", np.int64),     # its samples seen by an armed gate,
    ("win_gated", np.int64),       # and the NIS values kept in the gated-NIS buffer
], align=True)
EVIDENCE_STATUS = np.dtype([
    ("n", np.int64),               # position samples in the sums
    ("s_yy", np.float64),          # their sum of y^T y
    ("broken", np.bool_),          # the rigid-body residual failed this episode
    ("arc", np.bool_),             # the sums began while the arm followed an arc (their noise is arc_ev_var)
], align=True)
RUN_PARAMS = np.dtype([(name, np.float64) for name in (
    "q_c",                         # m^2/s, the contact's random walk
    "corr",                        # IMU samples per proprioception sample
    "var_p",                       # m^2, TCP position noise
    "var_wn",                      # (rad/s)^2, per-sample object-rate noise
    "radial_var",                  # (m/s)^2, the arc follower's distrust along the lever arm
    "gate_nis",                    # the NIS gate (0: off)
    "k_mean",                      # eta ratio's prior mean (where k is held when not a state)
    "k_prior_var",                 # and its prior variance (0 when held)
    "max_block",                   # samples per collapsed update
    "ev_var",                      # m^2, the position evidence's noise (floored)
    "window_s",                    # s, the consistency window
    "tau_s",                       # s, the consistency ratio's smoothing
    "ev_min_samples",              # positions before the residual test can speak
    "ev_limit",                    # residual over expectation above which positions are no evidence
    "arc_ev_var",                  # m^2, the positions' noise while following an arc (0: not evidence then)
)], align=True)

Window = namedtuple("Window", "x0 P0 A b")       # the consistency window: start state, its prior, information
# PositionEvidence's state: counts, the integrated rotation (theta), G and the gripper's part of it, the
# regression's running sums (of X, X^T X, X^T y, y) and the marginal information handed over (lam, xi)
Evidence = namedtuple("Evidence", "status theta g g_tcp s_x s_xx s_xy s_y lam xi")
# A chunk of samples as the compiled run takes them (ContactKF): world frame, one row per sample. w,
# w_tcp and p are what the position evidence integrates; v is the held TCP velocity and w_v, w_tcp_v,
# p_v what it pairs with from when it was measured; fresh marks a new proprioception sample.
Samples = namedtuple("Samples", "dt w w_tcp p v w_v w_tcp_v p_v var_v var_w fresh")
Frame = namedtuple("Frame", "E nrm origin")      # the filter's coordinates: basis (d x 3), normal, onset TCP
# Everything the run updates in place: the state x, P, the counts (STATUS), the lever arm at the last
# sample, the consistency window and the position evidence. (The window's gated-NIS buffer is passed
# beside it: it is replaced when it grows.)
EkfState = namedtuple("EkfState", "x P status r_last win ev")
Outputs = namedtuple("Outputs", "x P r s")      # per reported segment: x, P, r_last, (steps, nis, consistency)



def record(dtype: np.dtype, **values) -> np.ndarray:
    """A one-element structured array of `dtype` (fields zero unless given): a named record the
    compiled run updates in place; read a field as rec[0]["name"]."""
    out = np.zeros(1, dtype)
    for name, value in values.items():
        out[0][name] = value
    return out


def contiguous(named):
    """The named tuple with each array C-contiguous (the compiled run's signatures ask for it; no copy
    when it already is)."""
    return type(named)(*(np.ascontiguousarray(a) for a in named))
