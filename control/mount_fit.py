"""The IMU's mount and clock, calibrated from motion (issue 48 §5): the gyro against the arm's own rate.

A gyro in the fingertip reads the gripper's rate in its own frame, `gyro(t + offset) = s R_imu_tcp
w_tcp(t) + b` while nothing turns the fingertip relative to the gripper (free motion). From the
arm's TCP orientations (its forward kinematics, as recorded) and the gyro, `fit_mount` finds the
rotation R_tcp_imu, the board's clock offset and the gyro's scale: for each trial offset the
rotation and scale are Wahba's problem (an SVD of the cross-covariance), and the offset is the one
with the least residual, refined to a tenth of a millisecond. Both sides are compared as rotation
increments over the states' intervals, so the states' rate sets the band the fit uses, and the
IMU's rate above it (vibration the encoders do not see, and the chip's noise) is reported apart.

`MountMonitor` keeps the same fit running in the daemon over free motion and says when the
configured mount or clock is off (warning `imu_mount`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import matrix_to_quat, quat_to_matrix

MIN_EXCITATION_RAD_S = 0.02     # RMS rate about every principal axis of the motion for a fit
MAX_OFFSET_S = 0.05             # the clock offsets tried: within +- this
OFFSET_STEP_S = 0.001           # ... first on this grid, then refined
OFFSET_REFINE_S = 0.0001
SPAN_S = 0.015                  # the arm's rotation is taken over intervals of at least this long


class ExcitationError(ValueError):
    """The motion did not turn the TCP about every axis: a one-line reason."""


@dataclass(frozen=True)
class MountFit:
    R_tcp_imu: np.ndarray          # the fitted mount, TCP <- IMU
    offset_s: float                # the board's stamps are this much later than the arm's for the same instant
    offset_sigma_s: float          # its one-sigma, from the residual's curvature about it (at least the grid's step)
    scale: float                   # the gyro's scale (1: as the full scale says)
    bias: np.ndarray               # the gyro's bias, IMU frame, rad/s
    residual_rad_s: float          # RMS of what the fit leaves, at the states' rate
    vibration_rad_s: float         # RMS of the IMU's rate above the states' band, less the chip's noise
    noise_rad_s: float             # RMS of the chip's white noise per sample
    excitation_rad_s: np.ndarray   # RMS of the arm's rate about its principal axes, descending
    intervals: int

    @property
    def quat(self) -> np.ndarray:
        """(x, y, z, w), TCP <- IMU."""
        return matrix_to_quat(self.R_tcp_imu)

    def angle_from_deg(self, R_tcp_imu_configured: np.ndarray) -> float:
        """How far the fitted mount is from a configured one, degrees."""
        return rotation_angle_deg(R_tcp_imu_configured.T @ self.R_tcp_imu)


def rotation_angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))))


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of rotation matrices (n, 3, 3) (angles well under pi)."""
    c = np.clip((np.einsum("nii->n", R) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(c)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.where(ang > 1e-9, ang / np.maximum(2.0 * np.sin(ang), 1e-12), 0.5)
    return v * s[:, None]


def body_increments(tcp_t: np.ndarray, tcp_quat: np.ndarray) -> np.ndarray:
    """The TCP's rotation over each state interval in its own frame (n - 1, 3), rad."""
    R = quat_to_matrix(np.asarray(tcp_quat, float))
    return _log(np.einsum("nji,njk->nik", R[:-1], R[1:]))


def _wahba(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, float]:
    """b ~ s M a + c for rotation M: (M, s, c, residual sum of squares), a and b (n, 3)."""
    am, bm = a.mean(axis=0), b.mean(axis=0)
    A, B = a - am, b - bm
    H = A.T @ B
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    M = Vt.T @ D @ U.T
    aa = float(np.einsum("ij,ij->", A, A))
    s = float(np.sum(S * np.diag(D))) / aa if aa > 0 else 1.0
    rss = float(np.einsum("ij,ij->", B, B)) - s * s * aa
    return M, s, bm - s * (M @ am), max(rss, 0.0)


class _Integral:
    """The gyro's running integral, for its mean over any interval: (G(t1) - G(t0)) / (t1 - t0)."""

    def __init__(self, t: np.ndarray, gyro: np.ndarray):
        self.t = t
        dt = np.diff(t)
        self.G = np.vstack([np.zeros(3), np.cumsum(0.5 * (gyro[1:] + gyro[:-1]) * dt[:, None], axis=0)])

    def at(self, ts: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(ts, self.t, self.G[:, k]) for k in range(3)])


def fit_mount(imu_t: np.ndarray, gyro: np.ndarray, tcp_t: np.ndarray, tcp_quat: np.ndarray,
              max_offset_s: float = MAX_OFFSET_S, min_excitation: float = MIN_EXCITATION_RAD_S) -> MountFit:
    """The mount, clock offset and gyro scale that fit a recording of free motion (module doc).
    ExcitationError (one line) when the motion did not turn the TCP about every axis."""
    imu_t, gyro = np.asarray(imu_t, float), np.asarray(gyro, float)
    tcp_t, tcp_quat = _spans(np.asarray(tcp_t, float), np.asarray(tcp_quat, float))
    inc = body_increments(tcp_t, tcp_quat)
    dt = np.diff(tcp_t)
    rate = inc / np.maximum(dt, 1e-9)[:, None]
    # only intervals the IMU covers at every offset tried
    ok = (tcp_t[:-1] - max_offset_s >= imu_t[0]) & (tcp_t[1:] + max_offset_s <= imu_t[-1]) \
        & (dt > 0.2 * float(np.median(dt)))             # a repeated or jittered stamp is no interval
    if int(np.count_nonzero(ok)) < 20:
        raise ExcitationError(f"the IMU and the arm's states overlap in {int(np.count_nonzero(ok))} state intervals;"
                              " at least 20 are needed")
    t0, t1, rate = tcp_t[:-1][ok], tcp_t[1:][ok], rate[ok]
    excitation = _excitation(rate)
    if excitation[-1] < min_excitation:
        axis = np.linalg.eigh(np.cov(rate.T))[1][:, 0]
        name = "xyz"[int(np.argmax(np.abs(axis)))]
        raise ExcitationError(f"the motion did not turn the TCP about every axis: about {np.round(axis, 2).tolist()}"
                              f" (TCP frame, mostly {name}) only {excitation[-1]:.3f} rad/s RMS, at least "
                              f"{min_excitation:g} needed; record small rotations about each TCP axis "
                              "(tecdard calibrate-mount --live)")
    G = _Integral(imu_t, gyro)

    def trial(off: float):
        b = (G.at(t1 + off) - G.at(t0 + off)) / (t1 - t0)[:, None]
        return _wahba(rate, b)

    grid = np.arange(-max_offset_s, max_offset_s + 1e-12, OFFSET_STEP_S)
    rss = np.array([trial(o)[3] for o in grid])
    best = float(grid[int(np.argmin(rss))])
    fine = np.arange(best - OFFSET_STEP_S, best + OFFSET_STEP_S + 1e-12, OFFSET_REFINE_S)
    rss_f = np.array([trial(o)[3] for o in fine])
    i = int(np.argmin(rss_f))
    offset = float(fine[i])
    M, s, c, r = trial(offset)
    offset_sigma = max(_offset_sigma(grid, rss, r, 3 * len(rate) - 7), _offset_spread(G, t0, t1, rate, M, s, c, grid))
    residual = math.sqrt(r / len(rate))
    vibration, noise = _above_band(imu_t, gyro, tcp_t, tcp_quat, M, s, c, offset)
    return MountFit(R_tcp_imu=M.T, offset_s=offset, offset_sigma_s=offset_sigma, scale=s, bias=c, residual_rad_s=residual,
                    vibration_rad_s=vibration, noise_rad_s=noise, excitation_rad_s=excitation, intervals=len(rate))


def _offset_sigma(grid: np.ndarray, rss: np.ndarray, rss_min: float, dof: int) -> float:
    """One sigma of the offset: the residual's variance over the curvature of the residual sum
    against the offset (a parabola through the coarse grid's five points about its least). The
    residual is not white (the arm's vibration), so this is a floor; never under the grid's step."""
    i = int(np.argmin(rss))
    lo, hi = max(i - 2, 0), min(i + 3, len(grid))
    if hi - lo < 3:
        return OFFSET_STEP_S
    a = float(np.polyfit(grid[lo:hi], rss[lo:hi], 2)[0])
    if a <= 0 or dof <= 0:
        return float(grid[-1] - grid[0])
    return max(math.sqrt(rss_min / dof / a), OFFSET_STEP_S)


def _offset_spread(G: "_Integral", t0, t1, rate, M, s, c, grid, parts: int = 4) -> float:
    """The offset's one sigma from its spread over `parts` contiguous parts of the recording, each
    fitted with the whole recording's mount, scale and bias: the residual's vibration is not white,
    and this sees what it does to the offset."""
    pred = s * (rate @ M.T) + c
    found = []
    for idx in np.array_split(np.arange(len(rate)), parts):
        if len(idx) < 5:
            continue
        err = [float(np.sum(((G.at(t1[idx] + o) - G.at(t0[idx] + o)) / (t1[idx] - t0[idx])[:, None]
                             - pred[idx]) ** 2)) for o in grid]
        found.append(float(grid[int(np.argmin(err))]))
    if len(found) < 2:
        return 0.0
    return float(np.std(found, ddof=1)) / math.sqrt(len(found))


def _spans(tcp_t: np.ndarray, tcp_quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every k-th state, so that each interval spans at least SPAN_S: a stamp's jitter (a tenth of a
    millisecond on a 1 kHz arm) is then a small part of the interval it divides the rotation by."""
    if len(tcp_t) < 3:
        return tcp_t, tcp_quat
    k = max(1, int(math.ceil(SPAN_S / float(np.median(np.diff(tcp_t))) - 1e-9)))
    return tcp_t[::k], tcp_quat[::k]


def _excitation(rate: np.ndarray) -> np.ndarray:
    """RMS of the rate about its principal axes, descending (rad/s)."""
    return np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(rate.T))[::-1], 0.0))


def _above_band(imu_t, gyro, tcp_t, tcp_quat, M, s, c, offset) -> tuple[float, float]:
    """(RMS of the IMU's rate above the states' band less the chip's noise; the noise's RMS per sample)."""
    inc = body_increments(tcp_t, tcp_quat)
    mid = 0.5 * (tcp_t[1:] + tcp_t[:-1]) + offset
    rate = inc / np.maximum(np.diff(tcp_t), 1e-9)[:, None]
    inside = (imu_t >= mid[0]) & (imu_t <= mid[-1])
    if int(np.count_nonzero(inside)) < 100:
        return 0.0, 0.0
    w = np.column_stack([np.interp(imu_t[inside], mid, rate[:, k]) for k in range(3)])
    r = gyro[inside] - (s * (w @ M.T) + c)
    # the part the states' band carries: r's mean over each state interval, held
    k = np.clip(np.searchsorted(tcp_t + offset, imu_t[inside], side="right") - 1, 0, len(tcp_t) - 2)
    sums = np.zeros((len(tcp_t) - 1, 3))
    np.add.at(sums, k, r)
    counts = np.bincount(k, minlength=len(tcp_t) - 1)[:, None]
    high = r - (sums / np.maximum(counts, 1))[k]
    noise = float(np.sqrt(np.mean(np.sum(np.diff(r, axis=0) ** 2, axis=1)) / 2.0))
    total = float(np.mean(np.sum(high ** 2, axis=1)))
    return math.sqrt(max(total - noise * noise, 0.0)), noise


class MountMonitor:
    """The fit kept running over the daemon's free motion (no contact episode, the gripper turning),
    as `fit_mount` makes it: over state intervals of at least SPAN_S, the TCP's rotation (its own
    frame, from the arm's attitudes) against the gyro's mean over the same interval shifted by each
    trial offset within +-10 ms, turned into the TCP frame with the configured mount; their
    cross-covariances summed. `add_state` takes each arm state, `add_imu` each IMU batch, `pause`
    the moments that are not free motion (a contact episode). `check()` says in one line when the
    mount is more than `max_deg` off once MIN_TURN_RAD has been turned about every axis, or the clock
    more than `max_offset_s` in CLOCK_CHECKS judgments in a row once CLOCK_MIN_TURN_RAD has; None
    otherwise."""

    OFFSETS_S = np.arange(-0.01, 0.0100001, 0.001)
    MIN_TURN_RAD = 0.5           # rotation seen about the weakest principal axis, summed, before judging
    CLOCK_CHECKS = 3             # judgments in a row that must find the clock off
    # The clock shows only where the rate changes: over the 25 s of `wrist` (1.2 rad about each axis)
    # it is within +-3 ms on the simulated rigs, so it is judged only after more turning than that
    CLOCK_MIN_TURN_RAD = 2.0
    MIN_RATE_RAD_S = 0.02        # intervals where the gripper turns slower than this carry nothing
    IMU_KEEP_S = 0.3             # the IMU's running integral kept this long

    def __init__(self, R_tcp_imu: np.ndarray, max_deg: float = 2.0, max_offset_s: float = 0.002):
        self.R = np.asarray(R_tcp_imu, float)
        self.max_deg, self.max_offset_s = max_deg, max_offset_s
        k = len(self.OFFSETS_S)
        self.n = np.zeros(k)
        self.sa, self.sb = np.zeros((k, 3)), np.zeros((k, 3))
        self.H = np.zeros((k, 3, 3))
        self.bb = np.zeros(k)
        self.a2 = np.zeros(k)                              # sum of |a|^2 per offset
        self.aa = np.zeros((3, 3))
        self.turned = 0.0                                  # s of intervals taken
        self.said = False
        self._clock_off = 0
        self.last: tuple[float, float] | None = None      # (degrees off, clock offset s) as last judged
        self._imu_t = np.zeros(0)                          # the IMU's running integral: stamps, values
        self._imu_G = np.zeros((0, 3))
        self._anchor: tuple[float, np.ndarray] | None = None   # the interval's first state (t, R)
        self._waiting: list = []                           # intervals whose IMU has not come yet

    def pause(self) -> None:
        """Not free motion from here (a contact turns the fingertip in the grasp): the next interval
        starts at the next state."""
        self._anchor = None
        self._waiting.clear()

    def add_state(self, t: float, R_world_tcp: np.ndarray) -> None:
        if self._anchor is None:
            self._anchor = (float(t), np.asarray(R_world_tcp, float))
            return
        t0, R0 = self._anchor
        if t - t0 < SPAN_S:
            return
        rate = _log((R0.T @ R_world_tcp)[None])[0] / (t - t0)
        self._anchor = (float(t), np.asarray(R_world_tcp, float))
        if float(rate @ rate) >= self.MIN_RATE_RAD_S ** 2:
            self._waiting.append((t0, float(t), rate))

    def add_imu(self, t: np.ndarray, gyro_imu: np.ndarray) -> None:
        """An IMU batch: its running integral, then every waiting interval it now covers."""
        if len(t) == 0:
            return
        if len(self._imu_t):
            prev_t, prev_g, G0 = self._imu_t[-1], self._last_g, self._imu_G[-1]
            tt = np.concatenate([[prev_t], t])
            gg = np.vstack([prev_g, gyro_imu])
        else:
            tt, gg, G0 = t, gyro_imu, np.zeros(3)
        G = G0 + np.vstack([np.zeros(3), np.cumsum(0.5 * (gg[1:] + gg[:-1]) * np.diff(tt)[:, None], axis=0)])
        if len(self._imu_t):
            tt, G = tt[1:], G[1:]
        self._last_g = gyro_imu[-1]
        keep = self._imu_t >= float(t[-1]) - self.IMU_KEEP_S
        self._imu_t = np.concatenate([self._imu_t[keep], tt])
        self._imu_G = np.vstack([self._imu_G[keep], G])
        lo, hi = float(self.OFFSETS_S.min()), float(self.OFFSETS_S.max())
        ready = [w for w in self._waiting if w[1] + hi <= self._imu_t[-1] and w[0] + lo >= self._imu_t[0]]
        self._waiting = [w for w in self._waiting if w[1] + hi > self._imu_t[-1] and w[0] + lo >= self._imu_t[0]]
        if not ready:
            return
        t0 = np.array([w[0] for w in ready])
        t1 = np.array([w[1] for w in ready])
        a = np.array([w[2] for w in ready])                                   # TCP frame, rad/s
        self.turned += float(np.sum(t1 - t0))
        for i, off in enumerate(self.OFFSETS_S):
            Gi = [np.interp(x, self._imu_t, self._imu_G[:, k]) for x in (t0 + off, t1 + off) for k in range(3)]
            mean = (np.column_stack(Gi[3:]) - np.column_stack(Gi[:3])) / (t1 - t0)[:, None]
            b = mean @ self.R.T                                                # TCP frame, configured mount
            self.n[i] += len(a)
            self.sa[i] += a.sum(axis=0)
            self.sb[i] += b.sum(axis=0)
            self.H[i] += a.T @ b
            self.bb[i] += float(np.einsum("ij,ij->", b, b))
            self.a2[i] += float(np.einsum("ij,ij->", a, a))
            if i == len(self.OFFSETS_S) // 2:
                self.aa += a.T @ a

    def check(self) -> str | None:
        """One line, once, when the configured mount or clock is off beyond the limits; else None."""
        if self.said or self.n[0] < 20:
            return None
        i0 = len(self.OFFSETS_S) // 2
        n = self.n[i0]
        cov = self.aa / n - np.outer(self.sa[i0] / n, self.sa[i0] / n)
        weakest = math.sqrt(max(float(np.linalg.eigvalsh(cov)[0]), 0.0))
        if weakest * self.turned < self.MIN_TURN_RAD:
            return None
        best, best_i, best_M = -np.inf, i0, np.eye(3)
        for i in range(len(self.OFFSETS_S)):
            Hc = self.H[i] - np.outer(self.sa[i], self.sb[i]) / self.n[i]
            U, S, Vt = np.linalg.svd(Hc)
            d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
            # the least residual with a rotation and a scale (Umeyama): the most of |b|^2 explained
            a2 = self.a2[i] - float(self.sa[i] @ self.sa[i]) / self.n[i]
            score = (S[0] + S[1] + d * S[2]) ** 2 / max(a2, 1e-12)
            if score > best:
                best, best_i, best_M = score, i, Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
        deg = rotation_angle_deg(best_M)
        offset = float(self.OFFSETS_S[best_i])
        self.last = (deg, offset)
        # the clock is weakly seen (only where the rate changes): off only when CLOCK_CHECKS judgments
        # in a row say so
        clock_seen = weakest * self.turned >= self.CLOCK_MIN_TURN_RAD
        self._clock_off = self._clock_off + 1 if clock_seen and abs(offset) > self.max_offset_s + 1e-6 else 0
        if deg > self.max_deg or self._clock_off >= self.CLOCK_CHECKS:
            self.said = True
            return (f"the IMU's configured mount looks {deg:.1f} deg off and its clock {offset * 1e3:+.0f} ms off "
                    f"(limits {self.max_deg:g} deg, {self.max_offset_s * 1e3:g} ms), from the gyro against the arm's "
                    "own rate: record free motion and run tecdard calibrate-mount")
        return None
