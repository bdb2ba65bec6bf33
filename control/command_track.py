"""What the daemon itself commanded the arm (CommandTrack): whether, at an instant, the arm's own
acceleration can have stepped.

An accelerometer onset waits for the arm's states (control.onset_guard.StepGuard), because an arm that
starts with an acceleration step shows it in the IMU at once and in its states only after their
latency. Where the daemon drives the arm, it knows better and sooner: each control tick sends joint
rates, and an arm whose commanded joint rates have held for `settle_s` has no step of its own to
take. A candidate onset at such an instant is decided at once (no wait for the states, no wait for
its ring to swing back).

A tick's commanded joint acceleration is its rates' change over its period, summed over the joints.
Beyond `steady_rad_s2` it is the arm's own motion: a start, a stop, a ramp, a hold. Under it, the
servo's own corrections: the daemon's approach at constant speed on the simulated arm commands
0.04-0.18 rad/s^2 (its feedback on the arm's noisy states; p50 0.09 over 72 ticks), its
starts and stops 0.5-2.5 rad/s^2. With the joints at most a metre from the TCP, `steady_rad_s2`
bounds what a tick asks of the TCP's acceleration in m/s^2, under the trigger's 0.4 m/s^2; the
kicks the corrections give the arm are part of the vibration the trigger's floor learns.

The envelope (docs/estimation.md): an arm that follows its joint-rate commands within `settle_s`
(the UR's speedJ at 4 rad/s^2 follows within a tick; franky's velocity motion is jerk-limited, so it
never steps). An arm moved by anyone else (a pendant, a program, the ROS 2 observer) sends no command
through the daemon: no instant is then steady, and the states decide as before.
"""
from __future__ import annotations

from collections import deque

import numpy as np

COMMAND_SETTLE_S = 0.1       # estimator.onset.command_settle_s
COMMAND_STEADY_RAD_S2 = 0.3   # estimator.onset.command_steady_rad_s2
COMMAND_HISTORY = 64          # ticks kept (1.3 s at 50 Hz)
COVER_GAPS = 1.5              # the commands cover an instant when the newest before it is this many ticks old at most


class CommandTrack:
    """The control ticks' joint-rate commands, in time order (`add`), and `steady(t)`."""

    def __init__(self, settle_s: float = COMMAND_SETTLE_S, steady_rad_s2: float = COMMAND_STEADY_RAD_S2):
        self.settle_s = float(settle_s)
        self.steady_rad_s2 = float(steady_rad_s2)
        self._ticks: deque = deque(maxlen=COMMAND_HISTORY)   # (t, changed since the tick before: bool)
        self._qd: np.ndarray | None = None
        self._t = -np.inf
        self._period = np.inf            # the ticks' period (the last gap's, at most a second)

    def add(self, t: float, qd) -> None:
        """A tick at t (s, the daemon's clock) that commanded joint rates qd (rad/s); older or repeated
        ticks are ignored (a replay hands over each once)."""
        t = float(t)
        if not t > self._t:
            return
        qd = np.asarray(qd, dtype=float)
        changed = True
        if self._qd is not None and qd.shape == self._qd.shape:
            dt = t - self._t
            changed = float(np.abs(qd - self._qd).sum()) > self.steady_rad_s2 * dt
            self._period = min(dt, 1.0)
        self._qd, self._t = qd, t
        self._ticks.append((t, changed))

    def steady(self, t: float) -> bool:
        """Whether the commands up to t (s) say the arm's own acceleration cannot have stepped at t: a
        tick within COVER_GAPS periods before t, ticks reaching back settle_s, and none in that span
        that commanded a joint acceleration beyond steady_rad_s2."""
        if self.settle_s <= 0.0 or not self._ticks:
            return False
        newest, reached = None, False
        for tk, changed in reversed(self._ticks):
            if tk > t:
                continue
            if newest is None:
                newest = tk
            if changed and t - tk < self.settle_s:
                return False
            if tk <= t - self.settle_s:
                reached = True           # the commands reach back over the whole settle_s
                break
        return newest is not None and reached and t - newest <= COVER_GAPS * self._period
