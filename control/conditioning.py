"""Gyro conditioning: rest bias, causal low-pass, IMU->world frames and the eta transmission scaling."""
from __future__ import annotations

import math

import numpy as np


def mean0(x: np.ndarray) -> np.ndarray:
    """x.mean(axis=0) to the last digit (numpy's mean is this sum and this division), without the
    wrapper's own cost: the idle pass takes a handful of these 100 times a second."""
    return np.add.reduce(x, axis=0) / len(x)


def moving_mean(hist: np.ndarray, x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The causal mean over the last w samples of each row of x (n, 3), continuing from hist (the
    last w - 1 rows before it, fewer at the start): (the means (n, 3), the rows to continue with).

    Cumulative sums over the history and the batch; once the history is full every window holds w
    samples and is a slice (the general case indexes each window's start)."""
    n_hist, n = len(hist), len(x)
    ext = np.concatenate([hist, x])
    c = np.concatenate([np.zeros((1, 3)), ext]).cumsum(axis=0)
    if n_hist >= w - 1:
        out = (c[n_hist + 1:n_hist + n + 1] - c[n_hist + 1 - w:n_hist + n + 1 - w]) / float(w)
    else:
        idx = np.arange(n_hist + 1, n_hist + n + 1)
        lo = np.maximum(idx - w, 0)
        out = (c[idx] - c[lo]) / (idx - lo)[:, None]
    return out, (ext[-(w - 1):].copy() if w > 1 else ext[:0].copy())


class GyroConditioner:
    """Turns raw IMU-frame gyro batches into the grasped object's angular velocity in the world.

    The fingertip gyro sees the gripper's own rotation in full and the object's
    rotation *relative to the gripper* attenuated by the soft fingertip, so
        w_imu_world = w_tcp + (w_obj - w_tcp) / eta
    and the object rate is recovered as
        w_obj = w_tcp + eta * (w_imu_world - w_tcp).
    """

    def __init__(self, R_tcp_imu: np.ndarray, bias_tau_s: float = 0.5, lpf_window: int = 1):
        if lpf_window < 1:
            raise ValueError("lpf_window: must be >= 1 sample")
        self.R_tcp_imu = np.asarray(R_tcp_imu, dtype=float)
        self.bias_tau_s = bias_tau_s
        self.lpf_window = lpf_window
        self.bias = np.zeros(3)        # rad/s, IMU frame
        self._bias_ready = False
        self._bias_s = 0.0             # rest time averaged into the bias so far
        self.bias_frozen = False
        self.bias_held = False         # the controller knows the tool touches something: hold the bias too
        self._hist = np.zeros((0, 3))  # last lpf_window-1 bias-free samples for the causal filter

    def track_bias(self, t: np.ndarray, gyro: np.ndarray) -> None:
        """Update the rest bias from a batch taken while no contact is tracked."""
        if self.bias_frozen or self.bias_held or len(t) == 0:
            return
        dt = float(t[-1] - t[0]) + 1e-4
        if not self._bias_ready:
            self.bias = mean0(gyro)
            self._bias_ready = True
            self._bias_s = dt
            return
        # A cumulative mean until bias_tau_s of rest has been seen, then exponential forgetting:
        # the first estimate is not one batch's noise.
        alpha = max(dt / (self._bias_s + dt), 1.0 - math.exp(-dt / self.bias_tau_s))
        self._bias_s += dt
        self.bias = self.bias + alpha * (mean0(gyro) - self.bias)

    def bias_state(self) -> np.ndarray:
        """(4,): the bias (rad/s, IMU frame) and the rest time averaged into it (s; 0: none yet), the
        state a replay starts from (tecdard.recording.replay.replay_live)."""
        return np.append(self.bias, self._bias_s if self._bias_ready else 0.0)

    def set_bias_state(self, state) -> None:
        self.bias = np.array(state[:3], dtype=float)
        self._bias_s = float(state[3])
        self._bias_ready = self._bias_s > 0.0

    def freeze_bias(self, frozen: bool = True) -> None:
        """Hold the bias during a contact episode (the object's rotation is not bias)."""
        self.bias_frozen = frozen

    @property
    def group_delay_samples(self) -> float:
        """Delay of the causal moving average, in samples."""
        return (self.lpf_window - 1) / 2.0

    def lowpass(self, gyro: np.ndarray) -> np.ndarray:
        """Bias-free, causally filtered gyro (IMU frame), moving average over lpf_window samples."""
        x = gyro - self.bias
        if self.lpf_window == 1:
            return x
        out, self._hist = moving_mean(self._hist, x, self.lpf_window)
        return out

    def object_rate_world(self, w_imu: np.ndarray, R_world_tcp: np.ndarray, w_tcp_world: np.ndarray,
                          eta) -> np.ndarray:
        """Object angular velocity in the world (n, 3) from filtered IMU-frame gyro (n, 3).

        R_world_tcp is (n, 3, 3) or (3, 3); w_tcp_world (n, 3) or (3,) is the gripper's own rate; eta
        a number or (n, 1), the transmission at each sample's grip force (measurements.EtaSchedule).
        """
        return w_tcp_world + eta * (self.imu_rate_world(w_imu, R_world_tcp) - w_tcp_world)

    def imu_rate_world(self, w_imu: np.ndarray, R_world_tcp: np.ndarray) -> np.ndarray:
        """The fingertip's own angular velocity in the world (n, 3) from filtered IMU-frame gyro (n, 3):
        object_rate_world before the gripper's rate and eta enter it. R_world_tcp (n, 3, 3) or (3, 3)."""
        w_tcp_imu = w_imu @ self.R_tcp_imu.T
        if R_world_tcp.ndim == 2:
            return w_tcp_imu @ R_world_tcp.T
        return (R_world_tcp @ w_tcp_imu[:, :, None])[:, :, 0]


def first_coincidence(t: np.ndarray, conds: dict, last_true: dict, window_s: float) -> int:
    """The first sample of t (n,) at which every condition (name -> (n,) bool) has been true within
    window_s, or -1; `last_true` (name -> time) carries each one's last true time over batches."""
    names = list(conds)
    last = np.empty((len(names), len(t)))
    for i, name in enumerate(names):
        true_t = np.where(conds[name], t, -np.inf)
        prev = last_true.get(name, -np.inf)
        last[i] = np.maximum.accumulate(np.concatenate([[prev], true_t]))[1:]
        last_true[name] = last[i, -1]
    ok = np.all(t[None, :] - last <= window_s, axis=0)
    idx = np.flatnonzero(ok)
    return int(idx[0]) if len(idx) else -1
