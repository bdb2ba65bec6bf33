"""`tecdard calibrate-eta REC.npz... --contact x,y,z | --radius r`: the fingertip's transmission
coefficient eta per grip force, from probes against a contact at a known place.

The fingertip's gyro sees a fraction of the held object's rotation relative to the gripper: the
pipeline's model (control/conditioning.py) is w_obj = w_tcp + eta (w_seen - w_tcp). With the contact
known, the object's rate follows from the TCP's motion alone: v_tcp = w_obj x r, r = p_tcp - p_c.
Its part across the lever arm is w_perp = r x v / |r|^2. So after the onset, in 10 ms windows
while the TCP moves, eta is the least-squares slope of (w_perp - w_tcp_perp) against
(w_seen_perp - w_tcp_perp). With `--radius` instead of a contact point, |w_obj - w_tcp| = |v_rel| / r
(the TCP on a circle of that radius about the contact).

Each recording gives one eta, with the standard error of its slope. The recordings at one grip
force (the `grip_force` key's median, rounded to 0.1 N) are pooled: the inverse-variance mean, and
the spread between recordings where there are several. The printed `estimator.eta_table` goes
into the daemon's config.

What is refused, one line each (exit 2): a grip force no gripper has (beyond the daemon's 0..1000 N),
a contact no lever arm reaches (under 1 mm or over 2 m from the TCP), an eta no fingertip has
(outside the daemon's (0, 100], or within two standard errors of zero), and recordings at one
grip force that disagree beyond their own errors: their chi-square, printed for every force with
the spread, over its 99.9 % quantile (two probes at eta 1.0 and 4.0 once pooled to 1.151 without
a word).

With `--contact`, the fingertip's lag (`estimator.fingertip_lag_s`) is fitted too: the twist the
gyro reads lags the object's by the silicone's time constant, which shows where the rates change
(the probe's start). At each proprioception sample in the first LAG_SPAN_S of the motion, the
object's rate relative to the gripper across the lever arm (from the TCP's velocity and the known
contact) is compared with eta times the gyro's relative rate LAG seconds later; the lag on a
LAG_STEP_S grid up to LAG_MAX_S that leaves the least residual over all the recordings (each with
its own eta) is the fingertip's. A best fit at LAG_MAX_S itself is refused (the true lag may lie
beyond). Steady motion says nothing about it, so a probe must start from rest.
"""
from __future__ import annotations

import numpy as np

from dataclasses import dataclass

from tecdard.control.geometry import quat_to_matrix
from tecdard.control.pipeline import MAX_ETA, MAX_GRIP_FORCE_N

WINDOW_S = 0.01               # samples averaged per window
MIN_SPEED_M_S = 0.002         # windows with a slower TCP carry no rate information
MIN_TURN_RAD = np.radians(2.0)    # a probe must turn the object at least this much
BIAS_WINDOW_S = 0.2           # the gyro bias: the mean over this long before the onset (at rest)
# The bias window ends this long before the onset: a probe's start from rest, with no impact, is found by
# the fingertip's twist and dated back to 3-10 ms after the arm began to move (control.onset)
ONSET_GUARD_S = 0.015
MIN_RECORDINGS = 2
FORCE_ROUND_N = 0.1
LAG_MAX_S = 0.020             # the fingertip lag searched, 0 to this (a best fit at it is said, best_lag)
LAG_STEP_S = 0.00025
LAG_SE_SPAN_S = 0.002        # the residual's curvature is fitted this far either side of its minimum
LAG_SPAN_S = 0.3              # the part of a probe fitted: its start (where the rates change) and enough to pin eta
MIN_LEVER_M, MAX_LEVER_M = 0.001, 2.0    # --contact's distance from the TCP, as --radius's bounds
CONSISTENCY_Z = 3.09          # recordings at one grip force agree when their chi-square is under its 99.9 % quantile


class CalibrationError(Exception):
    """What keeps a calibration from being made, in one line naming the file or the option."""


class NotAtRest(CalibrationError):
    """The arm moved in the bias window before the onset: that recording is left out, said in a line."""


REST_SPEED_M_S = 0.001        # the TCP is at rest below this (the gyro bias window before the onset)
REST_RATE_RAD_S = 0.005       # and the gripper turns slower than this
RATE_HALF_SPAN = 2            # the gripper's rate from its orientations: a slope over this many samples either side


def check_rest(name: str, rec, onset_t: float) -> None:
    """The gyro's bias is its mean over BIAS_WINDOW_S before the onset, which holds only if the arm was
    at rest then (a probe sent right after a `home` once read eta 2.04 against 1.98)."""
    sel = (rec.tcp_t >= onset_t - ONSET_GUARD_S - BIAS_WINDOW_S) & (rec.tcp_t < onset_t - ONSET_GUARD_S)
    if np.count_nonzero(sel) < 2:
        return
    # over the whole window, so that the encoders' noise averages out (one sample's rate reads 1-2 deg/s)
    idx = np.flatnonzero(sel)
    span = float(rec.tcp_t[idx[-1]] - rec.tcp_t[idx[0]])
    if span <= 0:
        return
    speed = float(np.linalg.norm(rec.tcp_pos[idx[-1]] - rec.tcp_pos[idx[0]])) / span
    R = quat_to_matrix(rec.tcp_quat[[idx[0], idx[-1]]])
    turn = float(np.arccos(np.clip((np.trace(R[0].T @ R[1]) - 1.0) / 2.0, -1.0, 1.0)))
    rate = turn / span
    if speed > REST_SPEED_M_S or rate > REST_RATE_RAD_S:
        raise NotAtRest(f"{name}: the arm moved in the {BIAS_WINDOW_S:g} s before the onset ({speed * 1e3:.1f} mm/s, "
                        f"{np.degrees(rate):.2f} deg/s): no gyro bias to take; left out (start probes from rest)")


def gripper_rates(rec, live=None) -> np.ndarray:
    """The gripper's own rate (world, rad/s) at each proprioception sample. From a daemon's recording
    (its live log, `live`), the rate the estimator took live: the arm's twist from its joint rates.
    Otherwise from the orientations: the least-squares slope of the rotation's track over
    RATE_HALF_SPAN samples either side. A one-interval difference of two noisy orientations (a
    Franka's or the simulator's encoders, 5e-5 rad at 65 Hz: about 5 mrad/s) swamped the gripper's
    own turn in a probe (about 1 mrad/s) and spread the fitted lag from probe to probe by 1.3 ms
    (0.8 ms with the arm's own rates, 0.95 ms with the slope)."""
    if live is not None:
        return np.asarray(live.tcp_w, dtype=float)
    R_world_tcp = quat_to_matrix(rec.tcp_quat)
    t = rec.tcp_t - rec.tcp_t[0]
    dR = np.einsum("kji,kjl->kil", R_world_tcp[:-1], R_world_tcp[1:])      # R_k^T R_{k+1}
    ang = np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    ax = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], axis=1)
    scale = np.where(ang > 1e-9, ang / np.maximum(2.0 * np.sin(ang), 1e-12), 0.5)
    step_world = np.einsum("kij,kj->ki", R_world_tcp[:-1], ax * scale[:, None])     # each interval's turn
    track = np.vstack([np.zeros((1, 3)), np.cumsum(step_world, axis=0)])          # (M, 3) rad
    # each sample's window [lo, hi) and its sums, from running sums
    n_all = len(t)
    k = np.arange(n_all)
    lo, hi = np.maximum(k - RATE_HALF_SPAN, 0), np.minimum(k + RATE_HALF_SPAN + 1, n_all)

    def window_sum(x):
        c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
        return c[hi] - c[lo]
    n = (hi - lo).astype(float)
    s_t, s_tt = window_sum(t), window_sum(t * t)
    s_x, s_tx = window_sum(track), window_sum(t[:, None] * track)
    den = n * s_tt - s_t * s_t
    return (n[:, None] * s_tx - s_t[:, None] * s_x) / np.where(den > 0, den, np.inf)[:, None]


def eta_of(name: str, rec, onset_t: float, contact=None, radius: float | None = None,
           live=None) -> tuple[float, float, int]:
    """(eta, its standard error, windows used) from one recording whose onset is at onset_t (`live`:
    its live log, for the gripper's rates: gripper_rates)."""
    t = rec.imu_t
    pre = (t < onset_t - ONSET_GUARD_S) & (t >= onset_t - ONSET_GUARD_S - BIAS_WINDOW_S)
    if np.count_nonzero(pre) < 10:
        raise CalibrationError(f"{name}: less than {BIAS_WINDOW_S:g} s at rest before the onset for the gyro bias")
    check_rest(name, rec, onset_t)
    bias = rec.gyro[pre].mean(axis=0)
    R_tcp_imu = quat_to_matrix(rec.imu_in_tcp_quat)
    R_world_tcp = quat_to_matrix(rec.tcp_quat)
    # proprioception at each IMU sample: the newest at or before it (causal, as the pipeline takes it)
    j = np.clip(np.searchsorted(rec.tcp_t, t, side="right") - 1, 0, len(rec.tcp_t) - 1)
    if rec.tcp_vel is not None:
        v_tcp = rec.tcp_vel
    else:
        v_tcp = np.gradient(rec.tcp_pos, rec.tcp_t, axis=0)
    w_tcp_k = gripper_rates(rec, live)
    after = t >= onset_t
    w_seen = np.einsum("kij,kj->ki", R_world_tcp[j], (rec.gyro - bias) @ R_tcp_imu.T)
    edges = np.arange(onset_t, t[-1], WINDOW_S)
    idx = np.searchsorted(t, edges)
    a_all, b_all = [], []
    turned = 0.0
    for k0, k1 in zip(idx[:-1], idx[1:]):
        if k1 - k0 < 3 or not after[k0]:
            continue
        jj = j[k0:k1]
        v = v_tcp[jj].mean(axis=0)
        wt = w_tcp_k[jj].mean(axis=0)
        ws = w_seen[k0:k1].mean(axis=0)
        turned += float(np.linalg.norm(ws - wt)) * (t[k1 - 1] - t[k0])
        if np.linalg.norm(v) < MIN_SPEED_M_S:
            continue
        if contact is not None:
            r = rec.tcp_pos[jj].mean(axis=0) - contact
            n2 = float(r @ r)
            if n2 < 1e-6:
                continue
            u = r / np.sqrt(n2)
            a = np.cross(r, v - np.cross(wt, r)) / n2                     # the object's rate relative to the gripper, across r
            b = (ws - wt) - ((ws - wt) @ u) * u
            a_all.append(a)
            b_all.append(b)
        else:
            v_rel = np.linalg.norm(v)
            a_all.append(np.array([v_rel / radius]))
            b_all.append(np.array([np.linalg.norm(ws - wt)]))
    if turned * 1.0 < MIN_TURN_RAD / 3.0 or len(a_all) < 5:       # the gyro sees 1/eta of the turn
        raise CalibrationError(f"{name}: the probe never turned the object (gyro saw {np.degrees(turned):.2f} deg "
                               f"relative to the gripper over {len(a_all)} moving windows)")
    a, b = np.concatenate(a_all), np.concatenate(b_all)
    bb = float(b @ b)
    eta = float(a @ b) / bb
    res = a - eta * b
    dof = max(len(a) - 1, 1)
    se = float(np.sqrt((res @ res) / dof / bb))
    return eta, se, len(a_all)


def lag_residuals(rec, onset_t: float, contact: np.ndarray, live=None) -> tuple[np.ndarray, np.ndarray, int]:
    """(lags on the grid (k,), the residual sum of squares at each, the residuals' count) of one
    recording with a known contact: the object's relative rate across the lever arm at each
    proprioception sample in the probe's first LAG_SPAN_S against the gyro's LAG later."""
    t = rec.imu_t
    pre = (t < onset_t - ONSET_GUARD_S) & (t >= onset_t - ONSET_GUARD_S - BIAS_WINDOW_S)
    bias = rec.gyro[pre].mean(axis=0)
    R_tcp_imu = quat_to_matrix(rec.imu_in_tcp_quat)
    R_world_tcp = quat_to_matrix(rec.tcp_quat)
    j_of_t = np.clip(np.searchsorted(rec.tcp_t, t, side="right") - 1, 0, len(rec.tcp_t) - 1)
    w_seen = np.einsum("kij,kj->ki", R_world_tcp[j_of_t], (rec.gyro - bias) @ R_tcp_imu.T)
    v_tcp = rec.tcp_vel if rec.tcp_vel is not None else np.gradient(rec.tcp_pos, rec.tcp_t, axis=0)
    sel = np.flatnonzero((rec.tcp_t >= onset_t - ONSET_GUARD_S) & (rec.tcp_t < onset_t + LAG_SPAN_S))
    lags = np.arange(0.0, LAG_MAX_S + 1e-12, LAG_STEP_S)
    rss = np.full(len(lags), np.inf)
    if len(sel) < 5:
        return lags, rss, 0
    r = rec.tcp_pos[sel] - contact
    n2 = np.einsum("ij,ij->i", r, r)
    u = r / np.sqrt(n2)[:, None]
    w_tcp = gripper_rates(rec, live)[sel]
    a = np.cross(r, v_tcp[sel] - np.cross(w_tcp, r)) / n2[:, None]   # the object's rate relative to the gripper, across r
    dt_imu = float(np.median(np.diff(t)))
    half = max(int(round(0.5 / (dt_imu * max(len(rec.tcp_t) / (rec.tcp_t[-1] - rec.tcp_t[0]), 1.0)))), 1)
    for k, lag in enumerate(lags):
        # the gyro's mean over the proprioception period around each sample's time + lag
        i = np.searchsorted(t, rec.tcp_t[sel] + lag)
        lo, hi = np.clip(i - half, 0, len(t)), np.clip(i + half + 1, 0, len(t))
        c = np.vstack([np.zeros((1, 3)), np.cumsum(w_seen, axis=0)])
        b = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)[:, None] - w_tcp
        b = b - np.einsum("ij,ij->i", b, u)[:, None] * u
        bb = float(np.sum(b * b))
        if bb <= 0:
            continue
        eta = float(np.sum(a * b)) / bb
        rss[k] = float(np.sum((a - eta * b) ** 2))
    return lags, rss, a.size


def lag_uncertainty(curves: list[np.ndarray], lags: np.ndarray, samples: int) -> float | None:
    """The lag's one-sigma: the larger of two. The summed residual's curvature about its minimum (a
    least-squares parabola over LAG_SE_SPAN_S either side): the lag at which the residual has grown
    by one sample's variance. And, with two probes or more, the scatter of each probe's own best lag
    (their standard deviation over the square root of their number): the residuals of one probe's
    start are not independent (the arm's motion and the gripper's rates are smooth), and the
    curvature alone once said 0.3 ms for three probes whose means spread by 0.5 ms. None where
    neither can be had. The lag shows only where the rates change, the probe's first tenth of a
    second, which proprioception samples a few times; it is printed so that a fit of 0 ms is not
    read as a measurement of none."""
    total = np.sum(np.vstack(curves), axis=0)
    k = int(np.argmin(total))
    near = np.abs(lags - lags[k]) <= LAG_SE_SPAN_S
    x, y = lags[near], total[near]
    sigmas = []
    if len(x) >= 5 and np.all(np.isfinite(y)) and samples > 3:
        c2, _, _ = np.polyfit(x - lags[k], y, 2)
        if c2 > 0:
            sigmas.append(float(np.sqrt(total[k] / (samples - 2) / c2)))
    own = []
    for curve in curves:
        try:
            own.append(best_lag([curve], lags))
        except LagAtBound:
            continue
    if len(own) >= 2:
        sigmas.append(float(np.std(own, ddof=1) / np.sqrt(len(own))))
    return max(sigmas) if sigmas else None


class LagAtBound(CalibrationError):
    """The residual is least at the end of the searched lags: the true lag may lie beyond."""


def best_lag(curves: list[np.ndarray], lags: np.ndarray) -> float:
    """The lag of least summed residual (a parabola through the grid's minimum and its neighbours).
    LagAtBound when that is the last lag searched: a silicone lags a few ms, a soft grasp's give
    can add more, and a fit pinned at the bound would be printed as if it were the answer."""
    total = np.sum(np.vstack(curves), axis=0)
    k = int(np.argmin(total))
    if k == len(lags) - 1:
        raise LagAtBound(f"--contact: the fingertip lag fits best at the end of the search, {lags[k] * 1e3:g} ms: "
                         f"it may be longer (a soft grasp's give); check the probes start from rest")
    if 0 < k < len(lags) - 1 and np.all(np.isfinite(total[k - 1:k + 2])):
        y0, y1, y2 = total[k - 1:k + 2]
        den = y0 - 2 * y1 + y2
        if den > 0:
            return float(lags[k] + 0.5 * (y0 - y2) / den * LAG_STEP_S)
    return float(lags[k])


@dataclass(frozen=True)
class Pooled:
    """The recordings at one grip force, pooled."""
    grip_force_n: float        # N
    eta: float                 # the inverse-variance mean
    sigma: float               # its one-sigma (widened to the spread where the recordings disagree more)
    n: int                     # recordings
    chi2: float                # sum of ((eta_i - eta) / se_i)^2: n - 1 when they agree within their errors
    spread: float              # max - min of the recordings' etas

    @property
    def dof(self) -> int:
        return self.n - 1

    @property
    def consistent(self) -> bool:
        """Within their own errors: chi2 under its 99.9 % quantile for n - 1 degrees of freedom."""
        return self.dof == 0 or self.chi2 <= chi2_quantile(self.dof, CONSISTENCY_Z)


def chi2_quantile(dof: int, z: float) -> float:
    """The chi-square quantile at the standard normal's z (Wilson-Hilferty; 11.1 for one degree of
    freedom at z 3.09, the exact 10.8)."""
    c = 2.0 / (9.0 * dof)
    return dof * (1.0 - c + z * np.sqrt(c)) ** 3


def pool(rows: list[tuple[float, float, float]]) -> list[Pooled]:
    """[(force, eta, se)] per recording -> one Pooled per grip force."""
    out = []
    for force in sorted({r[0] for r in rows}):
        group = [(e, s) for f, e, s in rows if f == force]
        e = np.array([g[0] for g in group])
        se = np.maximum(np.array([g[1] for g in group]), 1e-6)
        w = 1.0 / se ** 2
        mean = float((w * e).sum() / w.sum())
        sigma = float(np.sqrt(1.0 / w.sum()))
        chi2 = float((((e - mean) / se) ** 2).sum())
        if len(group) > 1:        # the recordings disagree more than their own errors say: take that
            sigma = max(sigma, float(e.std(ddof=1) / np.sqrt(len(group))))
        out.append(Pooled(force, mean, sigma, len(group), chi2, float(e.max() - e.min())))
    return out


def outliers(rows: list[tuple[float, str, float, float]]) -> list[tuple[str, str]]:
    """[(force, name, eta, se)] -> [(name, why)] for each recording whose eta disagrees with the others
    at its grip force beyond CONSISTENCY_Z of their combined error (leave-one-out; three or more
    recordings at a force, so that the others say which one is off: 0.72 among 1.98 and 2.00)."""
    out = []
    for force in sorted({r[0] for r in rows}):
        group = [r for r in rows if r[0] == force]
        if len(group) < 3:
            continue
        for _, name, eta, se in group:
            others = [(e, s) for _, n, e, s in group if n != name]
            (rest,) = pool([(force, e, s) for e, s in others])
            z = abs(eta - rest.eta) / np.hypot(se, rest.sigma)
            if z > CONSISTENCY_Z:
                out.append((name, f"eta {eta:.3f} +- {se:.3f} against {rest.eta:.3f} +- {rest.sigma:.3f} of the "
                                  f"other {len(others)} at grip {force:g} N ({z:.1f} sigma)"))
    return out


def check_fit(name: str, eta: float, se: float) -> None:
    """A recording's eta must be one a fingertip can have: in (0, MAX_ETA] as the daemon's own
    estimator.eta_table takes it, and told apart from zero (eta > 2 se); CalibrationError otherwise."""
    if not (np.isfinite(eta) and np.isfinite(se)) or not 0.0 < eta <= MAX_ETA:
        raise CalibrationError(f"{name}: eta {eta:.3f} +- {se:.3f} is no fingertip's (the daemon takes (0, "
                               f"{MAX_ETA:g}]); check --contact or --radius against the probe's geometry")
    if eta <= 2.0 * se:
        raise CalibrationError(f"{name}: eta {eta:.3f} +- {se:.3f} cannot be told from zero; the probe says "
                               "nothing of it (check --contact or --radius, and that the probe turned the object)")


def check_lever(name: str, rec, onset_t: float, contact) -> None:
    """The contact must be where a fingertip's lever arm can reach: MIN_LEVER_M..MAX_LEVER_M from the
    TCP after the onset (--contact 1e6,1e6,1e6 once gave an eta of -0.000 and exit 0)."""
    after = rec.tcp_t >= onset_t
    r = float(np.median(np.linalg.norm(rec.tcp_pos[after if after.any() else slice(None)] - contact, axis=1)))
    if not MIN_LEVER_M <= r <= MAX_LEVER_M:
        raise CalibrationError(f"--contact: {r:.4g} m from the TCP in {name}; a lever arm is {MIN_LEVER_M:g}.."
                               f"{MAX_LEVER_M:g} m (world frame, metres)")


def is_idle_capture(rec) -> bool:
    """A daemon's recording of a contact onset with no task running (the arm's own motion, or a
    bump): no probe of a known contact."""
    meta = rec.meta or {}
    return "robot" in meta and meta.get("reason") == "episode" and meta.get("task") is None


def grip_force_of(name: str, rec) -> float:
    f = None
    if rec.grip_force is not None:
        f = float(np.median(rec.grip_force))
    elif isinstance(rec.meta.get("grip_force"), (int, float)) and not isinstance(rec.meta["grip_force"], bool):
        try:
            f = float(rec.meta["grip_force"])
        except OverflowError:  # an integer beyond any float
            f = float("inf")
    if f is None:
        raise CalibrationError(f"{name}: no grip force (neither a grip_force key nor meta.grip_force)")
    if not np.isfinite(f) or not 0.0 <= f <= MAX_GRIP_FORCE_N:
        raise CalibrationError(f"{name}: grip force {f:.6g} N is no gripper's "
                               f"(the daemon takes 0..{MAX_GRIP_FORCE_N:g} N)")
    return round(f / FORCE_ROUND_N) * FORCE_ROUND_N


def table_yaml(pooled: list[Pooled]) -> str:
    return "estimator.eta_table: [" + ", ".join(f"[{p.grip_force_n:g}, {p.eta:.3f}]" for p in pooled) + "]"


def add_parser(sub) -> None:
    p = sub.add_parser("calibrate-eta", help="eta per grip force from probes against a contact at a known place")
    p.add_argument("recordings", nargs="+", help="REC.npz ... (each with a grip_force key or meta.grip_force)")
    p.add_argument("--contact", help="the contact's position x,y,z (world, m)")
    p.add_argument("--radius", type=float, help="or the lever arm from the TCP to the contact (m)")
    p.add_argument("--config", help="YAML whose `estimator` section finds the onsets")
    p.set_defaults(func=main)


def _contact(args) -> np.ndarray | None:
    """--contact as a point (m), None without one; ValueError naming what is wrong."""
    if args.contact is None:
        return None
    try:
        contact = np.array([float(x) for x in args.contact.split(",")])
    except ValueError:
        contact = None
    if contact is None or contact.shape != (3,) or not np.all(np.isfinite(contact)):
        from tecdard.safejson import show
        raise ValueError(f"--contact: expected three numbers x,y,z in metres, got {show(args.contact)}")
    return contact


def main(args) -> int:
    """`tecdard calibrate-eta`: the eta table (and the fingertip's lag with --contact); exit 2 with one line."""
    import argparse
    import pathlib

    from tecdard.tools.args import BadInput, estimates, recording_and_pipeline, refused

    def bad(msg: str) -> int:
        return refused("calibrate-eta", msg)

    if (args.contact is None) == (args.radius is None):
        return bad("give the contact's position (--contact x,y,z, world, m) or the lever arm (--radius r, m)")
    try:
        contact = _contact(args)
    except ValueError as exc:
        return bad(str(exc))
    if args.radius is not None and not (np.isfinite(args.radius) and 0.001 <= args.radius <= 2.0):
        return bad(f"--radius: expected 0.001..2 m, got {args.radius!r}")
    if len(args.recordings) < MIN_RECORDINGS:
        return bad(f"needs at least {MIN_RECORDINGS} recordings (got {len(args.recordings)}): eta's uncertainty "
                   "comes from more than one probe")
    curves, counts, lags, names = {}, {}, None, []
    try:
        for path in args.recordings:
            one = argparse.Namespace(recording=path, config=args.config, method=None, ignore_live=False,
                                     no_plane=False)
            rec, live, pipeline = recording_and_pipeline(one)
            _, onset_t, _ = estimates(one, rec, live, pipeline)
            name = pathlib.Path(path).name
            if is_idle_capture(rec):
                print(f"{name}: an idle capture (a contact onset with no task running): left out")
                continue
            if onset_t is None:
                raise CalibrationError(f"{name}: no contact onset detected")
            force = grip_force_of(name, rec)
            if contact is not None:
                check_lever(name, rec, onset_t, contact)
            try:
                eta, se, n = eta_of(name, rec, onset_t, contact, args.radius, live)
            except NotAtRest as exc:
                print(str(exc))
                continue
            check_fit(name, eta, se)
            names.append((force, name, eta, se))
            if contact is not None:
                lags, rss, count = lag_residuals(rec, onset_t, contact, live)
                curves[name] = rss
                counts[name] = count
            assumed = " (assumed: the daemon's estimator.grip_force_n)" if rec.meta.get("grip_force_assumed") else ""
            print(f"{name}: grip {force:g} N{assumed}, eta {eta:.3f} +- {se:.3f} ({n} windows)")
    except (BadInput, CalibrationError) as exc:
        return bad(str(exc))
    for name, why in outliers(names):
        print(f"{name}: an outlier, left out: {why}")
        names = [r for r in names if r[1] != name]
        curves.pop(name, None)
        counts.pop(name, None)
    if len(names) < MIN_RECORDINGS:
        return bad(f"{len(names)} recording(s) left to fit; needs at least {MIN_RECORDINGS}")
    rows = [(f, e, se) for f, _, e, se in names]
    lag_curves = list(curves.values())
    pooled = pool(rows)
    print("grip force N | eta | one-sigma | recordings | chi-square / dof | spread")
    for p in pooled:
        agree = f"{p.chi2:.1f} / {p.dof}" if p.dof else "-"
        print(f"{p.grip_force_n:12g} | {p.eta:.3f} | {p.sigma:.3f} | {p.n} | {agree} | {p.spread:.3f}")
    apart = [p for p in pooled if not p.consistent]
    if apart:
        p = apart[0]
        each = ", ".join(f"{e:.3f} +- {se:.3f} in {n}" for f, n, e, se in names if f == p.grip_force_n)
        return bad(f"grip {p.grip_force_n:g} N: the recordings disagree beyond their errors ({each}; chi-square "
                   f"{p.chi2:.1f} for {p.dof} degrees of freedom, over {chi2_quantile(p.dof, CONSISTENCY_Z):.1f}): "
                   "no table; probe again, or calibrate them apart")
    print(table_yaml(pooled))
    if lag_curves:
        try:
            lag = best_lag(lag_curves, lags)
            se = lag_uncertainty(lag_curves, lags, sum(counts.values()))
            said = "" if se is None else f"   # +- {se:.4f} s (one-sigma, from {len(lag_curves)} probes' starts)"
            print(f"estimator.fingertip_lag_s: {lag:.4f}{said}")
            if lag < LAG_STEP_S:
                print("the lag fits best at 0: the fingertip's lag is under the search's step, or the probes' "
                      "starts were too few or too smooth to show it")
        except LagAtBound as exc:            # eta stands; the lag is not found
            return bad(str(exc))
    return 0
