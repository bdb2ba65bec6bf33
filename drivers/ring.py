"""Bounded single-producer/single-consumer ring buffer of IMU samples (t, gyro xyz, accel xyz)."""
from __future__ import annotations

import math
import threading
import time

import numpy as np

COLUMNS = 7  # t, gx, gy, gz, ax, ay, az
# The alarm's level: the accelerometer's mean, following the stream with this time constant (the
# arm's own acceleration and gravity's turn change it slowly; an impact's first packet does not).
ALARM_LEVEL_TAU_S = 0.05
# ... and a sample alarms only beyond ALARM_SPREAD_K times the largest distance from the level that the
# stream has shown lately (a peak decaying with ALARM_SPREAD_TAU_S): on an arm that moves and vibrates,
# the raw stream strays from its level by more than the trigger's threshold all the time (the trigger
# judges what the arm's motion and vibration leave), and an alarm on every packet would run the trigger
# on every packet. An impact that stands out less than that waits for the estimator's batch, as before.
ALARM_SPREAD_K = 1.5
ALARM_SPREAD_TAU_S = 0.2


class SampleRing:
    """Preallocated ring; the producer pushes batches, the consumer pops batches.

    When the consumer falls behind by more than `capacity` samples the oldest
    are overwritten and counted in `overwritten`: acquisition never blocks.
    """

    def __init__(self, capacity: int = 65536):
        if capacity < 64:
            raise ValueError("capacity: must be >= 64 samples")
        self.capacity = capacity
        self._buf = np.zeros((capacity, COLUMNS))
        self._head = 0          # total samples ever written
        self._tail = 0          # total samples ever read
        self._cond = threading.Condition()
        self.overwritten = 0
        self.last_t = float("-inf")   # time of the newest sample, s (read without the lock)
        # The consumer is woken once the samples it waits for are there, not by every push (a board's
        # packet is 8 samples; the estimator waits for one or two output periods of them): at 6.7 kHz
        # that is some 70 wake-ups a second instead of hundreds.
        self._want = 1
        # The batch the consumer asked for last, kept between its pops: how many samples the producer
        # may let gather before it delivers (`shortfall`). `hurry` is set when the consumer wants less.
        self._want_next = 1
        self.hurry = threading.Event()
        self._due_t = 0.0             # when the push that satisfied the waiting consumer notified it
        self.wake = None              # optional: .note(late_s, now) gets each wait from then to running again
        # A pushed accelerometer sample this far from the stream's level (m/s^2; inf: off) ends the
        # consumer's wait at once, whatever batch it waits for: the onset trigger sees an impact's
        # packet as it comes (the consumer sets it from the trigger's threshold; `alarms` counts them).
        self.alarm_m_s2 = math.inf
        self.alarms = 0
        self._level: np.ndarray | None = None   # (3,) m/s^2, the producer's
        self._spread = 0.0                      # m/s^2, the producer's: the decaying peak distance from the level

    def push(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        n = len(t)
        if n == 0:
            return
        skipped = 0
        if n > self.capacity:
            skipped = n - self.capacity
            t, gyro, accel = t[-self.capacity:], gyro[-self.capacity:], accel[-self.capacity:]
            n = self.capacity
        alarm = self._alarmed(t, accel)
        with self._cond:
            self.overwritten += skipped
            start = self._head % self.capacity
            first = min(n, self.capacity - start)
            buf = self._buf
            buf[start:start + first, 0] = t[:first]
            buf[start:start + first, 1:4] = gyro[:first]
            buf[start:start + first, 4:7] = accel[:first]
            if first < n:
                rest = n - first
                buf[:rest, 0] = t[first:]
                buf[:rest, 1:4] = gyro[first:]
                buf[:rest, 4:7] = accel[first:]
            self._head += n
            if self._head - self._tail > self.capacity:
                self.overwritten += self._head - self._tail - self.capacity
                self._tail = self._head - self.capacity
            self.last_t = float(t[-1])
            if alarm:
                self.alarms += 1
                self._want = 1
            if self._head - self._tail >= self._want:
                self._due_t = time.monotonic()
                self._cond.notify()

    def _alarmed(self, t: np.ndarray, accel: np.ndarray) -> bool:
        """Whether a sample of the pushed accel (n, 3) is alarm_m_s2 or more from the level before it, and
        ALARM_SPREAD_K times the stream's recent spread; the level and the spread then follow the push."""
        if self.alarm_m_s2 == math.inf:
            self._level, self._spread = None, 0.0
            return False
        level = accel[0] if self._level is None else self._level
        dev = float(np.abs(accel - level).max())
        hit = dev >= max(self.alarm_m_s2, ALARM_SPREAD_K * self._spread)
        span = float(t[-1] - t[0]) * len(t) / max(len(t) - 1, 1)
        alpha = 1.0 - math.exp(-span / ALARM_LEVEL_TAU_S) if span > 0.0 else 1.0
        self._level = level + alpha * (accel.mean(axis=0) - level)
        self._spread = max(self._spread * math.exp(-span / ALARM_SPREAD_TAU_S), dev)
        return hit

    def pop(self, max_n: int = 1024, timeout: float = 0.05, min_n: int = 1) -> np.ndarray:
        """Up to max_n oldest unread samples as an (n, 7) copy, once at least min_n are there or
        after `timeout` s with what there is (empty without data)."""
        with self._cond:
            self._want_next = max(min_n, 1)
            if self._head - self._tail < min_n:
                self._want = max(min_n, 1)
                woken = self._cond.wait_for(lambda: self._head - self._tail >= self._want, timeout)
                self._want = 1
                if woken and self.wake is not None:
                    now = time.monotonic()
                    self.wake.note(now - self._due_t, now)
            n = min(self._head - self._tail, max_n)
            if n <= 0:
                return self._buf[:0].copy()
            start = self._tail % self.capacity
            end = start + n
            if end <= self.capacity:
                out = self._buf[start:end].copy()
            else:
                out = np.vstack([self._buf[start:], self._buf[:end - self.capacity]])
            self._tail += n
            return out

    def shortfall(self) -> int:
        """Samples still to come before the consumer's batch (as it last asked) is complete: until then
        a producer that delivers them later delays nothing."""
        return max(self._want_next - (self._head - self._tail), 0)

    def lower_want(self, n: int) -> None:
        """The consumer now wants batches of n samples or fewer: a wait for more ends once n are there,
        and a producer waiting on `hurry` delivers at once."""
        n = max(int(n), 1)
        with self._cond:
            self._want_next = min(self._want_next, n)
            if self._want > n:
                self._want = n
                if self._head - self._tail >= n:
                    self._due_t = time.monotonic()
                    self._cond.notify()
        self.hurry.set()

    def __len__(self) -> int:
        return self._head - self._tail

    @property
    def total(self) -> int:
        return self._head
