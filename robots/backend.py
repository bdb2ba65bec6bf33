"""Robot backend interfaces: reading state apart from commanding, in the manner of ur_rtde."""
from __future__ import annotations

import threading
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
    tcp_pose: np.ndarray | None = None    # oMtcp (4 x 4, world) as the robot reports it, from its own calibrated
                                          # kinematics and TCP setting; None: the daemon's FK of q
    grip_force: float | None = None       # the gripper's grasp force, N, where the robot reads one (eta's
                                          # schedule); None: estimator.grip_force_n, the configured constant


def joint_rates(qd, nq: int) -> np.ndarray:
    """A joint velocity command as an array, or ValueError naming what is wrong with it."""
    qd = np.asarray(qd, dtype=float)
    if qd.shape != (nq,) or not np.all(np.isfinite(qd)):
        raise ValueError(f"qd: expected {nq} finite joint rates")
    return qd


class StateSlot:
    """The newest JointState of a robot link, between the thread that receives states and the
    threads that read them: `publish` replaces it and wakes the waiters; `close` (the link has gone)
    wakes them for good, and reads then raise `error()`."""

    def __init__(self, error):
        self._error = error                  # () -> the exception to raise once closed or before a state
        self._state: JointState | None = None
        self._cond = threading.Condition()
        self.closed = threading.Event()

    def publish(self, js: JointState) -> None:
        with self._cond:
            self._state = js
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed.set()
            self._cond.notify_all()

    def read(self) -> JointState:
        if self._state is None:
            raise self._error()
        return self._state

    def wait(self, seq: int, timeout: float) -> JointState:
        """The newest state once its seq differs from `seq`, or after `timeout` s."""
        with self._cond:
            self._cond.wait_for(lambda: self.closed.is_set() or (self._state is not None and self._state.seq != seq),
                                timeout)
        if self.closed.is_set():
            raise self._error()
        return self.read()


CHILD_STOP_S = 2.0      # a robot link's child process is waited for this long, then terminated


def kill_child(proc) -> None:
    """Terminate a child process that is still alive, and wait for it."""
    if proc is not None and proc.is_alive():
        proc.terminate()
        proc.join(CHILD_STOP_S)


def end_child(proc, conns) -> None:
    """A child process that has been asked to stop: wait for it, terminate it if it does not, and
    close the parent's ends of its pipes (a link that reconnects makes new ones)."""
    proc.join(CHILD_STOP_S)
    kill_child(proc)
    for conn in conns:
        conn.close()


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
