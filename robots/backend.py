"""Robot backend interfaces: reading state apart from commanding, in the manner of ur_rtde."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass
class JointState:
    """Proprioception as a robot reports it: joint positions and rates on the daemon's clock."""
    t: float                 # monotonic time of the measurement, s
    q: np.ndarray            # rad
    qd: np.ndarray           # rad/s
    seq: int = 0             # increments with every new measurement
    tcp_twist: np.ndarray | None = None   # [v; w] world-aligned, m/s and rad/s, when the robot reports it
    tcp_force: np.ndarray | None = None   # external force on the TCP, world, N, when the robot estimates it


def joint_rates(qd, nq: int) -> np.ndarray:
    """A joint velocity command as an array, or ValueError naming what is wrong with it."""
    qd = np.asarray(qd, dtype=float)
    if qd.shape != (nq,) or not np.all(np.isfinite(qd)):
        raise ValueError(f"qd: expected {nq} finite joint rates")
    return qd


class RobotReceive(Protocol):
    """Reading side: latest proprioception."""

    def read_state(self) -> JointState: ...

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s (every new
        measurement, for the estimator, at the robot's own rate)."""
        ...


class RobotControl(Protocol):
    """Commanding side: joint velocity streaming, and a hold."""

    def command_joint_velocity(self, qd: np.ndarray) -> None: ...

    def hold(self) -> None: ...
