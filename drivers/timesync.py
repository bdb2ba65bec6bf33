"""MCU clock -> host monotonic clock: t0_us unwrapping and a drift-tracking fit on the arrival lower envelope."""
from __future__ import annotations

import collections

import numpy as np

WRAP_US = 1 << 32
BIN_S = 0.5                # one lower-envelope point per bin of MCU time
WINDOW_BINS = 60           # fit over the last 30 s
RESET_JUMP_S = 0.25        # a residual this large means the MCU clock jumped (restart) or the link stalled
RESET_LATE_PACKETS = 20    # this many late packets in a row: the MCU clock jumped backwards, refit
REFIT_SLEW_RATE = 5e-3     # a refit's change of the mapping is spread at this many seconds per second
SLEW_WINDOW_S = 2.0         # SlewClock: the arrivals' lower envelope over this much of the device's time
SLEW_RATE = 2e-3            # SlewClock: its offset moves at most this many seconds per second
# The envelope moved up: the last STEP_BINS bins' minima all lie more than STEP_TOL_S above the line under the
# window. No real board's free-running counter loses time, but a simulator's clock does whenever the simulator
# stalls (its time stops while the host's runs on), and so would a board whose counter was paused. The bins before
# those are left out and the line is fitted again, and the mapping moves to it at SLEW_RATE: the robot's clock
# (SlewClock) follows the same step after the same SLEW_WINDOW_S at the same rate, so where one simulator stamps
# both, the fingertip's samples and the arm's states stay together. (Following a step at once after 1 s split
# them by the 10-70 ms a loaded host's simulator runs late: franky-sim rotates diverged 55-110x or found the hinge
# 14-18 mm off.) A step beyond RESET_JUMP_S restarts a board's clock (RESET_LATE_PACKETS) but never a robot's,
# whose states that late read stale.
STEP_BINS = round(SLEW_WINDOW_S / BIN_S)
STEP_TOL_S = 0.002


class Unwrapper:
    """uint32 microsecond counter -> monotonically increasing seconds."""

    def __init__(self):
        self._last: int | None = None
        self._base = 0

    def reset(self) -> None:
        self._last = None
        self._base = 0

    def __call__(self, t_us: int) -> float:
        if self._last is not None and t_us < self._last and self._last - t_us > WRAP_US // 2:
            self._base += WRAP_US
        self._last = t_us
        return (self._base + t_us) * 1e-6


def lower_envelope_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, intercept) of the line under every point (x increasing) that lies highest at their mean x:
    the linear program of Moon, Skelly and Towsley ("Estimation and removal of clock skew from network
    delay measurements", INFOCOM 1999), solved on the points' lower convex hull. An arrival is never early,
    so a point above the envelope is a late one (a stalled read, a backlog taken at once) and never tilts
    the line; a least-squares fit through the bins' minima took a start-up backlog for a clock 3.4 % slow.
    Where the mean falls on a hull vertex, the flatter of its two edges."""
    hull: list[int] = []
    for i in range(len(x)):                        # Andrew's monotone chain, lower half
        while len(hull) >= 2:
            o, a = hull[-2], hull[-1]
            if (x[a] - x[o]) * (y[i] - y[o]) - (y[a] - y[o]) * (x[i] - x[o]) <= 0.0:
                hull.pop()                         # a lies on or above the chord o-i
            else:
                break
        hull.append(i)
    if len(hull) == 1:
        return 0.0, float(y[hull[0]])
    center = float(np.mean(x))
    best = None
    for i, j in zip(hull[:-1], hull[1:]):
        if x[i] <= center <= x[j]:
            slope = float((y[j] - y[i]) / (x[j] - x[i]))
            if best is None or abs(slope) < abs(best[0]):
                best = (slope, float(y[i] - slope * x[i]))
    assert best is not None                        # the hull spans every x, so some edge holds the mean
    return best


class ClockSync:
    """Maps MCU time to the host's monotonic clock.

    Each packet gives a pair (MCU time of its last sample, host time of its
    arrival); arrival = true host time + latency >= 0, so the lower envelope of
    (host - mcu) follows the clock offset and its drift. Per bin of BIN_S the
    minimum is kept; the line under the last WINDOW_BINS minima (their lower
    envelope, `lower_envelope_line`) gives host = a + b * mcu. Mapped times therefore include the link's minimum
    latency, a constant of the USB path. Drift of 100 ppm moves the offset by
    0.1 ms per second and is tracked within the window.
    """

    def __init__(self):
        self._bins: collections.deque = collections.deque(maxlen=WINDOW_BINS)   # (mcu, offset)
        self._bin_index: int | None = None
        self._bin_min: tuple[float, float] | None = None
        self.a = None        # host = a + b * mcu (+ the refit's correction, below)
        self.b = 1.0
        self.resets = 0
        self._late = 0
        self._last_mcu = None
        self._corr0 = 0.0    # a refit's jump at _corr_m0, taken out at _corr_rate from there
        self._corr_m0 = 0.0
        self._corr_rate = REFIT_SLEW_RATE
        self._corr_done_s = 0.0

    def reset(self) -> None:
        self._bins.clear()
        self._bin_index = None
        self._bin_min = None
        self.a = None
        self.b = 1.0
        self._late = 0
        self._corr0 = 0.0
        self._corr_rate = REFIT_SLEW_RATE
        self.resets += 1

    def add(self, mcu_s: float, host_s: float) -> None:
        self._last_mcu = mcu_s
        offset = host_s - mcu_s
        if self.a is not None:
            resid = offset - (self.a + (self.b - 1.0) * mcu_s)
            if resid < -RESET_JUMP_S:
                self.reset()               # arrived before it was sampled: the MCU clock jumped
            elif resid > RESET_JUMP_S:
                self._late += 1            # one stalled transfer is not a clock change; a run of them is
                if self._late >= RESET_LATE_PACKETS:
                    self.reset()
            else:
                self._late = 0
        index = int(mcu_s // BIN_S)
        if self._bin_index is None or index != self._bin_index:
            if self._bin_min is not None:
                self._bins.append(self._bin_min)
                self._fit()
            self._bin_index = index
            self._bin_min = (mcu_s, offset)
        elif offset < self._bin_min[1]:
            self._bin_min = (mcu_s, offset)
        if self.a is None:
            self.a, self.b = self._bin_min[1], 1.0
        elif len(self._bins) < 2 and offset < self.a + (self.b - 1.0) * mcu_s:
            self.a = offset            # early on: the lowest offset seen so far

    def _fit(self) -> None:
        before = None if self.a is None or self._last_mcu is None else float(self.to_host(self._last_mcu))
        stepped = self._refit()
        if before is not None:
            # no jump where the new fit takes over: the difference is taken out at REFIT_SLEW_RATE (each bin's
            # refit moved samples by milliseconds when arrivals were noisy), a step's at a robot clock's SLEW_RATE
            # (the refits while a step's correction is still being taken out keep its rate)
            stepping = self._corr_rate == SLEW_RATE and self._last_mcu - self._corr_m0 < self._corr_done_s
            self._corr0 = before - (self.a + self.b * self._last_mcu)
            self._corr_m0 = self._last_mcu
            self._corr_rate = SLEW_RATE if stepped or stepping else REFIT_SLEW_RATE
            self._corr_done_s = abs(self._corr0) / self._corr_rate    # MCU time after which none is left

    def _correction(self, mcu_s):
        if self._corr0 == 0.0:
            return 0.0
        m = np.asarray(mcu_s)
        if (m.flat[0] if m.ndim else m) - self._corr_m0 >= self._corr_done_s:
            # slewed out (a packet's times increase: its first is its earliest): the same +-0 the sum
            # below gives, without its five numpy calls for every packet until the next refit
            return 0.0
        # np.clip's bounds without its wrapper (a packet's times are mapped 840 times a second)
        left = np.minimum(np.maximum(abs(self._corr0) - self._corr_rate * (m - self._corr_m0), 0.0),
                          abs(self._corr0))
        return np.copysign(left, self._corr0)

    def _refit(self) -> bool:
        """Fit the line under the window's bins; True when the envelope had stepped up (the bins before it left)."""
        stepped = False
        pts = np.array(self._bins)
        if len(pts) >= 3:
            slope, intercept = lower_envelope_line(pts[:, 0] - pts[0, 0], pts[:, 1])
            if len(pts) > STEP_BINS:
                recent = pts[-STEP_BINS:]
                above = recent[:, 1] - (intercept + slope * (recent[:, 0] - pts[0, 0]))
                if np.all(above > STEP_TOL_S):       # the envelope stepped up: the bins before the step go
                    for _ in range(len(pts) - STEP_BINS):
                        self._bins.popleft()
                    # the clock's rate is the window's (a step moved its offset, not its rate): the line under the
                    # recent bins at that slope
                    pts, stepped = recent, True
                    intercept = float(np.min(pts[:, 1] - slope * (pts[:, 0] - pts[0, 0])))
            self.b = 1.0 + slope
            self.a = intercept - slope * pts[0, 0]
        else:
            self.a, self.b = float(pts[:, 1].min()), 1.0
        return stepped

    def to_host(self, mcu_s: np.ndarray) -> np.ndarray:
        return self.a + self.b * np.asarray(mcu_s) + self._correction(mcu_s)


class SlewClock:
    """Maps a steady device clock (a robot controller's) to the host's monotonic clock as
    host = device + offset. The offset follows the lower envelope of (arrival - device time) over
    the last SLEW_WINDOW_S, but moves at most SLEW_RATE seconds per second of device time, so
    consecutive mapped times keep their spacing within 0.2 % and never go back, once SLEW_WINDOW_S
    has passed since it started: until then a lower envelope is taken at once, as ClockSync takes
    its first second's (the first arrivals may be late). An arrival RESET_JUMP_S early (a clock that
    jumped ahead) starts it afresh; arrivals RESET_JUMP_S late are stale states, never a reason to
    move it at once (ClockSync takes a run of them for a board that restarted).

    ClockSync fits a line through 0.5 s bins for a board's crystal, whose drift matters over
    minutes; a refit by milliseconds (noisy arrivals: a loaded host, a simulator's clock) taken at
    once made proprioception a few microseconds apart read as a turn of hundreds of rad/s. A
    robot's clock drifts by ppm: an offset that slews is enough. Both follow a step of the
    envelope below RESET_JUMP_S after SLEW_WINDOW_S at SLEW_RATE, so two devices stamped by one
    clock stay together."""

    def __init__(self):
        self.offset: float | None = None
        self._env: collections.deque = collections.deque()    # (device_s, offset) candidates, increasing
        self._last_device = None
        self.resets = 0
        self._fresh_until = -np.inf

    def add(self, device_s: float, host_s: float) -> None:
        if device_s == self._last_device:
            return      # a state repeated (a frozen controller): no news of the clock, and never a reason to restart it
        cand = host_s - device_s
        if self.offset is not None and cand - self.offset < -RESET_JUMP_S:
            # an arrival RESET_JUMP_S before its mapped time: the clock jumped ahead (slewed, the states would read
            # fresher than they are for minutes): afresh. Arrivals that late are never taken for a clock that lost
            # time, unlike ClockSync's board: states that late are stale (robot_stale), and a clock that lost time
            # reads the same; the link's reconnect restarts it after a controller's restart
            self._env.clear()
            self.offset = None
            self.resets += 1
        env = self._env
        while env and env[-1][1] >= cand:
            env.pop()                       # a later, lower candidate makes older higher ones moot
        env.append((device_s, cand))
        while env[0][0] < device_s - SLEW_WINDOW_S:
            env.popleft()
        target = env[0][1]
        if self.offset is None or self._last_device is None or device_s - self._last_device > SLEW_WINDOW_S:
            self.offset = target            # the first sample, or after a gap: start afresh
            # the arrivals it starts from may be late (a backlog draining, a simulator running behind): for a window
            # the envelope is taken down at once (slewed, a first state 70 ms late left them all late for 35 s)
            self._fresh_until = device_s + SLEW_WINDOW_S
        elif device_s < self._fresh_until and target < self.offset:
            self.offset = target
        else:
            step = SLEW_RATE * max(device_s - self._last_device, 0.0)
            self.offset += min(max(target - self.offset, -step), step)
        self._last_device = device_s

    def to_host(self, device_s: float) -> float:
        return device_s + self.offset
