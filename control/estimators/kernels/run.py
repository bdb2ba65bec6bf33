"""The whole `ekf` run of a batch, compiled: every block of a chunk, the consistency window and the
position evidence in one call (ekf_advance), and a batch's segments between the pipeline's outputs in
one call (ekf_segments). Their state and parameters are the named records of `records`."""
from __future__ import annotations

import math

import numpy as np
from numba import types

from tecdard.control.estimators.kernels import jit
from tecdard.control.estimators.kernels.constants import K_MIN
from tecdard.control.estimators.kernels.evidence import position_account, position_reset
from tecdard.control.estimators.kernels.linalg import window_add, window_nis
from tecdard.control.estimators.kernels.model import block_update
from tecdard.control.estimators.kernels.nbtypes import FRAME_T, OUTPUTS_T, PARAMS_T, SAMPLES_T, STATE_T


@jit(types.float64[::1](STATE_T, types.float64[::1], types.float64[:, :], types.float64[:, :], types.float64[:],
                        types.float64, types.float64[:], types.int64, PARAMS_T))
def window_account(state, gbuf, P_prior, A, b, duration, nis, rejected, prm):
    """One committed block into the consistency window (ContactKF's divergence statistic, see
    docs/estimation.md); state.x is the state before the block, P_prior its prior, (A, b) the block's
    information, nis the block's per-sample NIS (empty when the gate was not armed). Returns gbuf, the
    buffer of the window's gated NIS, grown when full.

    The window's data are one collapsed measurement of the state at its start (window_add); its NIS
    against the prior there, over its rank, smoothed over prm.tau_s, is the consistency ratio. A
    window whose samples the gate mostly rejected reads at least their median NIS over d."""
    x, status, win = state.x, state.status, state.win
    d = state.r_last.shape[0]
    st = status[0]
    pr = prm[0]
    ng = st.win_gated
    if rejected:
        m = nis.shape[0]
        if ng + m > gbuf.shape[0]:
            grown = np.empty(max(2 * gbuf.shape[0], ng + m))
            grown[:ng] = gbuf[:ng]
            gbuf = grown
        gbuf[ng:ng + m] = nis
        ng += m
    st.win_gated = ng
    st.win_samples += nis.shape[0]
    if st.win_blocks == 0:
        win.x0[:] = x
        win.P0[:, :] = P_prior
        win.A[:, :] = A
        win.b[:] = b
    else:
        window_add(win.A, win.b, win.x0, x, A, b)
    st.win_blocks += 1
    st.win_t += duration
    t_w = st.win_t
    if t_w < pr.window_s:
        return gbuf
    n_samples = st.win_samples
    st.win_blocks = 0
    st.win_t = 0.0
    st.win_samples = 0
    st.win_gated = 0
    ratio = 0.0
    w_nis, rank = window_nis(win.A, win.b, win.P0)
    if rank:
        # the excess over the expectation referred to the nominal length: batching cannot change it
        ratio = 1.0 + (max(w_nis, 0.0) / rank - 1.0) * (pr.window_s / t_w)
    if ng:
        over = 0
        for i in range(ng):
            if gbuf[i] > pr.gate_nis:
                over += 1
        if 2 * over > n_samples:
            ratio = max(ratio, np.median(gbuf[:ng]) / d)
    if not rank and ratio <= 0.0:
        return gbuf
    alpha = 1.0 - math.exp(-t_w / pr.tau_s)
    st.consistency += alpha * (ratio - st.consistency)
    return gbuf


@jit(types.float64[::1](STATE_T, types.float64[::1], SAMPLES_T, types.int64, types.int64, FRAME_T, PARAMS_T,
                        types.boolean, types.boolean))
def ekf_advance(state, gbuf, smp, i0, i1, frame, prm, use_fresh, ev_on):
    """`ekf` over the samples i0:i1 of a chunk, all state updated in place; returns the gated-NIS buffer.

    state (records.EkfState): x, P (the filter), status (STATUS), r_last (the lever arm at the last
    sample), the consistency window (win, and gbuf: its gated NIS) and, with ev_on, the position
    evidence (ev). The samples `smp` (records.Samples, n rows): dt, w and w_tcp (world: the object's
    rate at the scheduled eta, the gripper's own rate, zeros when still), p, v (TCP), what v pairs
    with from when it was measured (w_v, w_tcp_v, p_v: block_update), var_v, var_w, and fresh (a new
    proprioception sample) when use_fresh; without it the position evidence restarts every block.
    frame: the filter's coordinates. prm: RUN_PARAMS.

    The chunk is one run of blocks of at most prm.max_block samples; the very first block of an
    episode is linearised about its own answer by two uncommitted passes."""
    x, P, status, r_last, ev = state.x, state.P, state.status, state.r_last, state.ev
    st = status[0]
    pr = prm[0]
    d = frame.E.shape[0]
    nk = x.shape[0] - d
    mb = int(pr.max_block)
    for b0 in range(i0, i1, mb):
        b1 = min(b0 + mb, i1)
        steps = st.steps
        gate = pr.gate_nis > 0 and steps > 0
        # at onset the noise model is linearised about a guess: two uncommitted passes on the first
        # block (from the same prior) linearise it about the data's own answer
        passes = 3 if steps == 0 else 1
        x_lin = x
        for i in range(passes):
            out = block_update(x, P, x_lin, smp, b0, b1, frame, prm, gate, i == passes - 1)
            x_lin = out[0]
        x_new, P_new, P_prior, A, b, gated, nis, rejected, w_d, r0, duration = out
        st.rejected += rejected
        if nis.shape[0]:
            st.nis = nis[-1]
        if steps > 0:
            gbuf = window_account(state, gbuf, P_prior, A, b, duration, nis, rejected, prm)
        x[:] = x_new
        P[:, :] = P_new
        st.steps += b1 - b0
        k = max(x[d], K_MIN) if nk else pr.k_mean
        for a in range(d):
            r_last[a] = r0[b1 - b0 - 1, a] - x[a] / k
        if not ev_on or (use_fresh and ev.status[0].broken):
            continue
        arc = pr.radial_var > 0
        if not use_fresh or (arc and pr.arc_ev_var <= 0.0):
            # no position measurements, or following an arc with positions no evidence: restart the reference
            position_reset(ev)
            continue
        if ev.status[0].arc != arc:
            # into or out of arc following: the grasp's compliance moves the TCP along the lever arm
            # by up to the admittance's lag, so the positions then have noise of their own (arc_ev_var)
            # and a reference of their own
            position_reset(ev)
            ev.status[0].arc = arc
        t_d = np.empty(w_d.shape)
        for i in range(b1 - b0):
            if d == 2:
                t_d[i, 0] = (smp.w_tcp[b0 + i, 0] * frame.nrm[0] + smp.w_tcp[b0 + i, 1] * frame.nrm[1]
                             + smp.w_tcp[b0 + i, 2] * frame.nrm[2])
            else:
                for a in range(3):
                    t_d[i, a] = smp.w_tcp[b0 + i, a]
        position_account(x, P, ev, smp.dt[b0:b1], w_d, t_d, r0, smp.fresh[b0:b1], d, prm)
    return gbuf


@jit(types.float64[::1](STATE_T, types.float64[::1], SAMPLES_T, FRAME_T, PARAMS_T, types.boolean, types.boolean,
                        types.float64, types.int64[::1], OUTPUTS_T))
def ekf_segments(state, gbuf, smp, frame, prm, use_fresh, ev_on, slip_radial_var, ends, out):
    """ekf_advance over the chunk's segments 0:ends[0], ends[0]:ends[1], ... (one call where the
    pipeline reports between segments), keeping the state after each of the first len(out.x) in
    `out` (records.Outputs): x, P, r_last, and (steps, nis, consistency). Returns the gated-NIS
    buffer.

    As between calls one segment at a time (ContactKF.radial_var_now): once the position evidence
    has broken, the segments after take the velocity along the lever arm with at least
    slip_radial_var."""
    i0 = 0
    for j in range(ends.shape[0]):
        if ev_on and state.ev.status[0].broken and prm[0].radial_var < slip_radial_var:
            prm[0].radial_var = slip_radial_var
        gbuf = ekf_advance(state, gbuf, smp, i0, ends[j], frame, prm, use_fresh, ev_on)
        i0 = ends[j]
        if j < out.x.shape[0]:
            out.x[j] = state.x
            out.P[j] = state.P
            out.r[j] = state.r_last
            out.s[j, 0] = state.status[0].steps
            out.s[j, 1] = state.status[0].nis
            out.s[j, 2] = state.status[0].consistency
    return gbuf
