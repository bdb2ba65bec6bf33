"""The one declared type of IMU source: the fingertip board on serial, the simulator's, whatever comes next.

A source turns its device's bytes (or simulated physics) into timestamped SI samples, and nothing
more: t on the host's monotonic clock (s), gyro in rad/s and accel in m/s^2 in the IMU frame. The
daemon reads `imu.source` once and asks the robot backend for the source (robots.backend.RobotBackend.
imu_source); the acquisition thread then only calls `read`.
"""
from __future__ import annotations

import numpy as np

from tecdard.drivers.lsm6dsr import Scaling


class ImuSource:
    """What the daemon asks of an IMU source. `read` and `odr_hz` are its own; the rest default to a
    source with nothing to open, report or check."""

    odr_hz: float       # the source's data rate, Hz (a board reports its own once it streams)

    def start(self) -> str | None:
        """Open the device now, or keep trying in the background (a board unplugged at start); the
        problem as one line, or None. Never raises."""
        return None

    def read(self, timeout: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The next chunk (t (n,), gyro (n, 3), accel (n, 3)), or None after `timeout` seconds."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device (a source whose device another owner stops has nothing to do)."""

    @property
    def part(self) -> str | None:
        """The sensor behind the source, for `status` and `tecdard imu`; None when the source cannot say."""
        return None

    @property
    def saturation(self) -> tuple[float, float]:
        """(gyro rad/s, accel m/s^2) at which a sample is clipped: the LSM6DSR's default full scales."""
        return Scaling().saturation

    def faults(self) -> dict[str, str]:
        """The source's own faults that hold now, code -> message (its port lost, its sensor silent), said as
        they stand (how long ago), for `status`; their events come through drain_events."""
        return {}

    def lost_s(self) -> float | None:
        """How long ago the source's device was lost (its port gone), None while it is there."""
        return None

    def drain_events(self) -> list[dict]:
        """The source's own events since the last call (a port lost, a port back), for the outbox."""
        return []

    def checks(self) -> list:
        """Whether this host can reach the device (tecdard.host.Check each), for `tecdard doctor`."""
        return []
