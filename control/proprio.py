"""The robot's recent TCP states (ProprioTrack), for causal lookup at each IMU sample's instant.

States arrive at the arm's rate (500 Hz-1 kHz) and are added one at a time; the contact pipeline and
the onset trigger read them once a batch: the TCP's pose, velocity and rate held from the newest
state at or before each time, what the arm's own motion explains of the IMU's readings, and how
noisy the positions are.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import relative_rotvec

PROPRIO_HISTORY = 256         # proprioception samples kept for causal lookup
DERIVED_V_FIRST_VAR = 1.0     # (m/s)^2 for the first sample when velocity must be derived
MAD_TO_SIGMA = 0.6745         # median |x| of a zero-mean normal, in its sigmas
WDOT_MAX_AGE_S = 0.05         # a reported TCP rate's last change is extrapolated at most this far
# The TCP's acceleration (what the onset trigger subtracts from the accelerometer) is the slope of a
# least-squares line through the velocities of the last ACCEL_WINDOW_S, and of at least ACCEL_MIN_STATES
# states: a single difference of reported velocities is 0.7 m/s^2 of noise at 500 Hz and 1 mm/s, the
# slope over 20 ms a twelfth of that. It trails a jerk-limited plan by half the window (5 m/s^3 x 10 ms:
# 0.05 m/s^2).
ACCEL_WINDOW_S = 0.02
ACCEL_MIN_STATES = 4
SPECIFIC_FORCE_AT_REST = np.array([0.0, 0.0, 9.81])   # world (z up): an accelerometer at rest reads +g up


HISTORY_SLACK = 4              # ProprioTrack's backing arrays hold this many windows of states
# ProprioTrack's fields and their initial values (a scalar, a row shape, or the identity). The
# history is a window of `size` states over backing arrays of HISTORY_SLACK * size: each field reads
# as a view of its backing array, moved one state on when the window is full, and the window is
# copied back to the start only once per (HISTORY_SLACK - 1) * size states (shifting 18 arrays on
# every state was a third of the estimator's time at rest). A state is written straight into the
# backing arrays, and the views are made again only when a reader asks after the window moved:
# states arrive at 500 Hz-1 kHz, readers once a batch.
HISTORY_FIELDS = {
    "t": np.inf,
    "p": (3,), "v": (3,),
    "tv": 0.0,                     # time the velocity belongs to
    "pv": (3,),                    # the TCP's position then
    "hv": 0.0,                     # half the span around tv that the velocity describes, s
    "var_v": 0.0,
    "a": 0.0,                      # |acceleration| estimate, m/s^2
    "acc": (3,),                   # the TCP's acceleration, world, m/s^2 (a fit over ACCEL_WINDOW_S)
    "acc_ok": False,               # acc[k] has been fitted
    # per state, what it says of the arm's own motion for the onset trigger (explained): the specific
    # force and the gripper's rate in the IMU frame, how far they may trail, |acceleration|
    "expl": (9,),
    "expl_ok": False,
    "alpha": 0.0,                  # |angular acceleration| estimate of the TCP, rad/s^2
    "tw": 0.0,                     # time the TCP rate belongs to
    "R": "eye",
    "w": (3,),
    "wdot": (3,),                  # angular acceleration of a reported TCP rate, rad/s^2 (0: derived)
    "grip_force_n": np.nan,        # the gripper's grasp force, N (nan: not measured)
}


@dataclass(frozen=True, slots=True)
class ProprioSample:
    """One robot state as the estimator takes it: made on the robot's reader thread (the daemon's
    ProprioFeed), handed to the estimator thread through its ring, fed to the pipeline, and kept for
    the recording. Declared once: what crosses from the arm to the estimator and into a file."""
    t: float                          # monotonic time of the measurement, s
    p_world: np.ndarray               # the TCP's position, world, m (3,)
    v_world: np.ndarray | None        # the TCP's velocity, world, m/s (None: derived from the positions)
    R_world_tcp: np.ndarray           # the TCP's orientation, world <- TCP (3, 3)
    w_world: np.ndarray | None        # the TCP's own angular rate, world, rad/s (None: derived)
    grip_force_n: float = np.nan      # the gripper's grasp force, N (nan: not measured)
    q: np.ndarray | None = None       # the joints, rad (for the recording: the export draws the arm)
    grip_width_m: float = np.nan      # the gripper's opening, m (nan: no gripper, or it cannot say)
    grasped: float = np.nan           # 1: the gripper holds something, 0: nothing, nan: it cannot say
    wrench: np.ndarray | None = None  # the arm's own estimate at the TCP, world: force N, torque N m (6,), nan where
                                      # it gives none (for the recording; None: the arm estimates no force)
    wrench_source: str = ""           # whose estimate (robots.backend.WRENCH_SOURCES' key)
    qd: np.ndarray | None = None      # the joints' measured rates, rad/s (for the recording: a dataset's state)


@dataclass(frozen=True, slots=True)
class TcpAt:
    """ProprioTrack.lookup's answer for times ts (n,): each row from the newest state at or before its time."""
    p: np.ndarray                     # (n, 3) TCP position, world, m, extrapolated with v
    v: np.ndarray                     # (n, 3) TCP velocity, world, m/s
    R: np.ndarray                     # (n, 3, 3) TCP orientation, world <- TCP
    w: np.ndarray                     # (n, 3) the TCP's own rate, world, rad/s
    var_v: np.ndarray                 # (n,) the velocity's variance with its staleness, (m/s)^2
    var_w: np.ndarray                 # (n,) the staleness variance of w, (rad/s)^2
    grip_force_n: np.ndarray          # (n,) N (nan: not measured)
    ok: np.ndarray                    # (n,) False before the first state
    stamp: np.ndarray                 # (n,) the stamp of the state each row used, s


def _backing(n: int, fill) -> np.ndarray:
    """A backing array of n rows for a field: a scalar fill (float or bool), a row shape, or "eye" (3x3)."""
    if fill == "eye":
        return np.tile(np.eye(3), (n, 1, 1))
    if isinstance(fill, tuple):
        return np.zeros((n, *fill))
    if isinstance(fill, bool):
        return np.full(n, fill, dtype=bool)
    return np.full(n, fill)


class ProprioTrack:
    """Recent TCP states for causal lookup: an IMU sample at time t sees only states stamped at or before t.

    Velocity is the robot's reported TCP velocity when given; otherwise the
    backward difference of the last two positions (which belongs to the middle
    of their interval). Each lookup carries a velocity variance: the source's
    noise plus the staleness of holding it (|a| * age)^2, with |a| from the
    last two velocities.
    """

    def __init__(self, size: int = PROPRIO_HISTORY, sigma_p: float = 5e-5, sigma_v: float = 1e-3):
        self.size = size
        self.sigma_p = sigma_p
        self.sigma_v = sigma_v
        self._backing = {name: _backing(HISTORY_SLACK * size, fill) for name, fill in HISTORY_FIELDS.items()}
        self._arrays = tuple(self._backing[name] for name in _WRITTEN)
        self._start = 0
        self._views_start = -1             # where the views were made (_window)
        self._views: dict[str, np.ndarray] = {}
        self._last = None                  # the newest state in plain floats (add): t, p, v, tv, w, tw, R
        self.imu_mount = np.eye(3)         # R_tcp_imu
        self.n = 0
        self._rate = np.nan
        self._rate_n = 0
        self._noise = 0.0
        self._noise_at = 0            # `added` when the noise was last measured
        self.added = 0                # samples added so far (the history itself is a window)

    def add(self, t: float, p: np.ndarray, v: np.ndarray | None, R: np.ndarray, w: np.ndarray | None,
            grip_force_n: float = np.nan) -> None:
        """One proprioception sample; v and w (the TCP's rate, world) may be None: derived then.
        In plain floats: the arithmetic is numpy's to the last digit (the same IEEE operations, one
        element at a time), without numpy's per-call cost on 3-vectors."""
        n, last = self.n, self._last
        t = float(t)
        if n and t <= last[0]:
            return   # repeated or out of order: keep time strictly increasing
        p = tuple(p.tolist()) if isinstance(p, np.ndarray) else tuple(map(float, p))
        R_list = R.tolist() if isinstance(R, np.ndarray) else [list(map(float, row)) for row in R]
        if n:
            t1, p1, v1, tv1, w1, tw1, R1 = last
        if v is None:
            if n:
                dt = t - t1
                v = ((p[0] - p1[0]) / dt, (p[1] - p1[1]) / dt, (p[2] - p1[2]) / dt)
                tv, var_v = t - dt / 2, 2 * self.sigma_p_effective() ** 2 / dt ** 2
                # the mean velocity over the interval
                pv, hv = (0.5 * (p[0] + p1[0]), 0.5 * (p[1] + p1[1]), 0.5 * (p[2] + p1[2])), dt / 2
            else:
                v, tv, var_v, pv, hv = (0.0, 0.0, 0.0), t, DERIVED_V_FIRST_VAR, p, 0.0
        else:
            # at its stamp; it stands for the half periods either side (the rate's mean over them)
            v = tuple(v.tolist()) if isinstance(v, np.ndarray) else tuple(map(float, v))
            tv, var_v, pv, hv = t, self.sigma_v ** 2, p, (t - t1) / 2 if n else 0.0
        wdot = (0.0, 0.0, 0.0)
        if w is None:
            # Backward difference of orientations: it belongs to the middle of the interval.
            if n:
                dt = t - t1
                r = relative_rotvec(R_list, R1)
                w, tw = (r[0] / dt, r[1] / dt, r[2] / dt), t - dt / 2
            else:
                w, tw = (0.0, 0.0, 0.0), t
        else:
            w = tuple(w.tolist()) if isinstance(w, np.ndarray) else tuple(map(float, w))
            tw = t
            if n and tw1 == t1:
                # two reported rates: extrapolate the rate between samples, not hold it
                dt = t - t1
                wdot = ((w[0] - w1[0]) / dt, (w[1] - w1[1]) / dt, (w[2] - w1[2]) / dt)
        a = math.dist(v, v1) / max(tv - tv1, 1e-6) if n else 0.0
        alpha = math.dist(w, w1) / max(tw - tw1, 1e-6) if n else 0.0
        if n == self.size:
            self._slide()
            n -= 1
        i = self._start + n
        for arr, value in zip(self._arrays, (t, p, v, tv, var_v, pv, hv, a, alpha, tw, R_list, w, wdot, grip_force_n,
                                             False, False)):
            arr[i] = value                               # acc and expl: fitted when first asked for (explained)
        self._last = (t, p, v, tv, w, tw, R_list)
        self.n = n + 1
        self.added += 1

    def _window(self) -> dict[str, np.ndarray]:
        """Each field's view of the current window (made again only after the window moved)."""
        if self._views_start != self._start:
            s, e = self._start, self._start + self.size
            self._views = {name: arr[s:e] for name, arr in self._backing.items()}
            self._views_start = self._start
        return self._views

    def _slide(self) -> None:
        """Drop the oldest state: the window moves on by one; at the end of the backing arrays, the
        newest size - 1 states go back to their start."""
        if self._start + self.size < len(self._backing["t"]):
            self._start += 1
        else:
            keep = self.size - 1
            for arr in self._backing.values():
                arr[:keep] = arr[self._start + 1:self._start + self.size]
            self._start = 0
            self._views_start = -1

    def _fit_accel(self, k: int) -> np.ndarray:
        """The TCP's acceleration as of state k: the slope of the least-squares line through the
        velocities of the last ACCEL_WINDOW_S up to it (at least ACCEL_MIN_STATES)."""
        if k == 0:
            return np.zeros(3)
        tv = self.tv[:k + 1]
        k0 = int(np.searchsorted(tv, tv[k] - ACCEL_WINDOW_S, side="left"))
        k0 = max(min(k0, k - ACCEL_MIN_STATES + 1), 0)
        dt = tv[k0:] - float(np.add.reduce(tv[k0:])) / (k + 1 - k0)
        den = float(dt @ dt)
        if den <= 0.0:
            return np.zeros(3)
        return (dt @ self.v[k0:k + 1]) / den

    def _fitted(self, k: int) -> np.ndarray:
        if not self.acc_ok[k]:
            self.acc[k] = self._fit_accel(k)
            self.acc_ok[k] = True
        return self.acc[k]

    def explained(self, ts: np.ndarray) -> np.ndarray | None:
        """What the arm's own motion accounts for at the IMU samples stamped ts (n,), from the state
        each holds (causal; samples before the first state take the first state's): (n, 9) rows of
        the specific force (gravity and the TCP's acceleration) and the gripper's rate, both in the
        IMU's frame (`imu_mount`: R_tcp_imu), half the change of the acceleration and of the rate
        over the ACCEL_WINDOW_S before the state (m/s^2, rad/s: how far a fit over that window may
        trail the arm), and |acceleration|. None before any state. Each state's row is made once."""
        if self.n == 0:
            return None
        j = np.maximum(np.searchsorted(self.t[:self.n], ts, side="right") - 1, 0)
        if not self.expl_ok[j[-1]] or not self.expl_ok[j[0]]:
            for k in range(int(j[0]), int(j[-1]) + 1):
                if not self.expl_ok[k]:
                    self._explain(k)
        return self.expl.take(j, axis=0)

    def accel_change(self, t_c: float) -> tuple[float, float]:
        """How far the arm's own acceleration (the ACCEL_WINDOW_S fit, world) moved after time t_c:
        (the largest |a_k - a_ref| over the states stamped after t_c, a_ref the fit at the last state
        at or before it, m/s^2; the newest state's stamp, s). (0, -inf) before any state."""
        n = self.n
        if n == 0:
            return 0.0, -math.inf
        t = self.t[:n]
        ref = int(np.searchsorted(t, t_c, side="right")) - 1
        if ref < 0 or ref >= n - 1:
            return 0.0, float(t[n - 1])
        a_ref = self._fitted(ref)
        change = max(math.sqrt(float(d @ d)) for d in (self._fitted(k) - a_ref for k in range(ref + 1, n)))
        return change, float(t[n - 1])

    def fit_span_s(self) -> float:
        """How long after an acceleration change the fit has taken it up: ACCEL_WINDOW_S, or
        ACCEL_MIN_STATES states at the arm's rate when they span more."""
        rate = self.rate_hz()
        if rate != rate:
            return ACCEL_WINDOW_S
        return max(ACCEL_WINDOW_S, (ACCEL_MIN_STATES - 1) / rate)

    def _explain(self, k: int) -> None:
        before = max(int(np.searchsorted(self.tv[:k + 1], self.tv[k] - ACCEL_WINDOW_S, side="right")) - 1, 0)
        acc = self._fitted(k)
        da = acc - self._fitted(before)
        dw = self.w[k] - self.w[before]
        M = self.R[k] @ self.imu_mount                      # world <- IMU
        row = self.expl[k]
        row[0:3] = (acc + SPECIFIC_FORCE_AT_REST) @ M
        row[3:6] = self.w[k] @ M
        row[6] = 0.5 * math.sqrt(float(da @ da))
        row[7] = 0.5 * math.sqrt(float(dw @ dw))
        row[8] = math.sqrt(float(acc @ acc))
        self.expl_ok[k] = True

    def sigma_p_effective(self) -> float:
        """The TCP position's noise, m: the configured sigma_p, or more where the positions show it.

        The configured value is a floor. A rig's actual noise can be ten times more (the paper's
        0.5 mm against an encoder's 0.05 mm), and a filter that trusts positions and the
        velocities derived from them ten times too much drifts. So the noise is measured from the
        positions' second differences, which cancel a steady motion: for white noise each has a
        variance of 6 sigma^2. Their median is robust to the starts and stops. Re-measured every
        16 samples over the history."""
        n = self.n
        if n < 8:
            return self.sigma_p
        if self._noise_at == 0 or self.added - self._noise_at >= 16:
            p = self.p[:n]
            d2 = p[2:] - 2.0 * p[1:-1] + p[:-2]
            self._noise = float(np.median(np.abs(d2))) / (MAD_TO_SIGMA * math.sqrt(6.0))
            self._noise_at = self.added
        return max(self.sigma_p, self._noise)

    def rate_hz(self) -> float:
        """Median proprioception rate, Hz (recomputed every 16 samples)."""
        if self.n < 3:
            return np.nan
        if self._rate_n == 0 or self.n - self._rate_n >= 16 or self.n < self._rate_n:
            self._rate = float(1.0 / np.median(np.diff(self.t[:self.n])))
            self._rate_n = self.n
        return self._rate

    def lookup(self, ts: np.ndarray) -> "TcpAt":
        """The TCP at times ts (n,), extrapolated from the newest state at or before each (TcpAt)."""
        f = self._window()
        t_j = f["t"]
        j = np.searchsorted(t_j[:self.n], ts, side="right") - 1
        ok = j >= 0
        j = np.maximum(j, 0)
        # take(): a row gather at a third of fancy indexing's cost on (n, 3) and (n, 3, 3) fields
        t_j, v_j, tw_j = t_j[j], f["v"].take(j, axis=0), f["tw"][j]
        age = ts - t_j
        p = f["p"].take(j, axis=0) + v_j * age[:, None]
        var_v = f["var_v"][j] + (f["a"][j] * (ts - f["tv"][j])) ** 2
        var_w = (f["alpha"][j] * (ts - tw_j)) ** 2
        # a reported TCP rate is extrapolated with its last change (a turning gripper's rate ramps;
        # held for up to a proprioception period it would enter the object rate times (eta - 1)), but
        # not without bound: when proprioception stalls, the rate is held after WDOT_MAX_AGE_S
        w = f["w"].take(j, axis=0) + f["wdot"].take(j, axis=0) * np.minimum(ts - tw_j, WDOT_MAX_AGE_S)[:, None]
        return TcpAt(p, v_j, f["R"].take(j, axis=0), w, var_v, var_w, f["grip_force_n"][j], ok, t_j)

    def rate_held(self, t: float) -> np.ndarray | None:
        """lookup's TCP rate (world, rad/s) at one time t, or None before the first state: the same
        arithmetic, for the idle pass's one question (whether the gripper turns)."""
        f = self._window()
        j = int(np.searchsorted(f["t"][:self.n], t, side="right")) - 1
        if j < 0:
            return None
        tw = f["tw"][j]
        return f["w"][j] + f["wdot"][j] * min(t - tw, WDOT_MAX_AGE_S)

    def rate_at(self, ts: np.ndarray) -> np.ndarray:
        """The TCP's own rate (world, rad/s) at times ts (n,): interpolated between the times the
        rates belong to (a derived rate to the middle of its interval), past the newest one
        extrapolated with the last change for at most WDOT_MAX_AGE_S."""
        n = self.n
        tw, w = self.tw[:n], self.w[:n]
        if n < 2:
            return np.tile(w[-1] if n else np.zeros(3), (len(ts), 1))
        if len(ts) > 1:
            # the times asked are a held state's, a few distinct ones per batch: each run of one time
            # is answered once (the same arithmetic, a tenth of the interpolations)
            new = np.empty(len(ts), dtype=bool)
            new[0] = True
            np.not_equal(ts[1:], ts[:-1], out=new[1:])
            if 2 * int(np.count_nonzero(new)) < len(ts):
                return self.rate_at(ts[new])[np.cumsum(new) - 1]
        out = np.column_stack([np.interp(ts, tw, w[:, a]) for a in range(3)])
        late = ts > tw[-1]
        if late.any():
            slope = (w[-1] - w[-2]) / max(tw[-1] - tw[-2], 1e-6)
            out[late] = w[-1] + np.minimum(ts[late] - tw[-1], WDOT_MAX_AGE_S)[:, None] * slope
        return out

    def velocity_at(self, ts: np.ndarray):
        """What the velocity held at times ts belongs to: (the TCP's position then (n, 3), the time
        tv it belongs to and the half span h around it that it describes (n,) each: a derived
        velocity the interval between its two positions, a reported one the half periods either
        side of its stamp; its noise variance, (m/s)^2, without staleness)."""
        j = np.maximum(np.searchsorted(self.t[:self.n], ts, side="right") - 1, 0)
        return self.pv.take(j, axis=0), self.tv[j], self.hv[j], self.var_v[j]


# the fields ProprioTrack.add writes, in the order it writes them (acc and expl are fitted later)
_WRITTEN = ("t", "p", "v", "tv", "var_v", "pv", "hv", "a", "alpha", "tw", "R", "w", "wdot", "grip_force_n",
            "acc_ok", "expl_ok")


def _window_field(name: str) -> property:
    return property(lambda self: self._window()[name], doc=f"the window's `{name}` (a view: HISTORY_FIELDS)")


for _name in HISTORY_FIELDS:
    setattr(ProprioTrack, _name, _window_field(_name))
assert set(_WRITTEN) | {"acc", "expl"} == set(HISTORY_FIELDS)
