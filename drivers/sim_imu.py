"""Simulated fingertip IMU (LSM6DSR-like): world kinematics in, timestamped SI samples out."""
from __future__ import annotations

import queue
from dataclasses import dataclass

import numpy as np

from control.geometry import quat_to_matrix

GRAVITY_WORLD_M_S2 = np.array([0.0, 0.0, -9.81])
DEG = np.pi / 180.0


@dataclass
class SimImuParams:
    odr_hz: float = 6667.0
    eta: float = 2.0                         # apparent transmission of the object's relative rotation
    gyro_noise_density: float = 5e-3 * DEG   # rad/s/sqrt(Hz)  (LSM6DSR: 5 mdps/sqrt(Hz))
    accel_noise_density: float = 60e-6 * 9.81  # m/s^2/sqrt(Hz) (LSM6DSR: 60 ug/sqrt(Hz))
    gyro_bias_max: float = 0.02              # rad/s, per-axis bias drawn uniformly in +-
    accel_bias_max: float = 0.05             # m/s^2
    onset_ring_m_s2: float = 2.0             # accelerometer ring amplitude when the object starts to move
    onset_ring_hz: float = 120.0
    onset_ring_tau_s: float = 0.015
    timestamp_jitter_s: float = 2e-6
    imu_in_tcp_quat: tuple = (0.0, 0.0, 0.0, 1.0)  # (x, y, z, w), TCP <- IMU

    @classmethod
    def from_config(cls, section, default_mount=None) -> "SimImuParams":
        d = cls()
        mount = list(default_mount) if default_mount is not None else list(d.imu_in_tcp_quat)
        return cls(
            odr_hz=section.getfloat("odr_hz", d.odr_hz, minval=100.0, maxval=20000.0),
            eta=section.getfloat("eta", d.eta, above=0.0),
            gyro_noise_density=section.getfloat("gyro_noise_density", d.gyro_noise_density, minval=0.0),
            accel_noise_density=section.getfloat("accel_noise_density", d.accel_noise_density, minval=0.0),
            gyro_bias_max=section.getfloat("gyro_bias_max", d.gyro_bias_max, minval=0.0),
            accel_bias_max=section.getfloat("accel_bias_max", d.accel_bias_max, minval=0.0),
            onset_ring_m_s2=section.getfloat("onset_ring_m_s2", d.onset_ring_m_s2, minval=0.0),
            onset_ring_hz=section.getfloat("onset_ring_hz", d.onset_ring_hz, above=0.0),
            onset_ring_tau_s=section.getfloat("onset_ring_tau_s", d.onset_ring_tau_s, above=0.0),
            timestamp_jitter_s=section.getfloat("timestamp_jitter_s", d.timestamp_jitter_s, minval=0.0),
            imu_in_tcp_quat=tuple(section.getquat("imu_in_tcp_quat", mount)),
        )


class SimImu:
    """The simulated device. The physics thread calls `feed()` with each slice of
    kinematics; `read()` hands the acquisition thread the samples, as a serial
    port would hand it bytes. Samples are (t, gyro, accel): seconds on the
    daemon's monotonic clock, rad/s and m/s^2 in the IMU sensor frame.
    """

    def __init__(self, params: SimImuParams, seed: int = 0, fifo_chunks: int = 512):
        self.p = params
        self.rng = np.random.default_rng(seed)
        self.R_tcp_imu = quat_to_matrix(np.array(params.imu_in_tcp_quat))
        self.gyro_bias = self.rng.uniform(-params.gyro_bias_max, params.gyro_bias_max, 3)
        self.accel_bias = self.rng.uniform(-params.accel_bias_max, params.accel_bias_max, 3)
        nyquist = params.odr_hz / 2.0
        self.gyro_sigma = params.gyro_noise_density * np.sqrt(nyquist)
        self.accel_sigma = params.accel_noise_density * np.sqrt(nyquist)
        self.period = 1.0 / params.odr_hz
        self._next_t = None
        self._rings: list[tuple[float, np.ndarray]] = []  # (start time, amplitude vector world)
        self._fifo: queue.Queue = queue.Queue(maxsize=fifo_chunks)
        self.dropped_chunks = 0
        self.samples = 0

    def feed(self, t: np.ndarray, w_tcp: np.ndarray, w_obj: np.ndarray, a_tcp: np.ndarray,
             R_world_tcp: np.ndarray, onsets: list[tuple[float, np.ndarray]] = ()) -> None:
        """Kinematic rows (m >= 2, world frame) -> IMU samples for times up to t[-1]."""
        for t0, direction in onsets:
            self._rings.append((t0, self.p.onset_ring_m_s2 * direction))
        if self._next_t is None:
            self._next_t = float(t[0])
        n = int(np.floor((t[-1] - self._next_t) / self.period)) + 1
        if n <= 0:
            return
        ts = self._next_t + self.period * np.arange(n)
        self._next_t = float(ts[-1] + self.period)
        ts_c = np.clip(ts, t[0], t[-1])

        def interp(arr):
            return np.stack([np.interp(ts_c, t, arr[:, i]) for i in range(3)], axis=1)

        wt, wo, at = interp(w_tcp), interp(w_obj), interp(a_tcp)
        R = R_world_tcp[-1]                     # orientation changes little within one slice
        R_world_imu = R @ self.R_tcp_imu
        w_seen = wt + (wo - wt) / self.p.eta
        gyro = w_seen @ R_world_imu + self.gyro_bias + self.rng.normal(0.0, self.gyro_sigma, (n, 3))
        f_world = at - GRAVITY_WORLD_M_S2
        for t0, amp in self._rings:
            dt = ts - t0
            live = dt >= 0
            if np.any(live):
                env = np.where(live, np.exp(-np.maximum(dt, 0) / self.p.onset_ring_tau_s)
                               * np.sin(2 * np.pi * self.p.onset_ring_hz * np.maximum(dt, 0)), 0.0)
                f_world = f_world + env[:, None] * amp
        self._rings = [(t0, a) for t0, a in self._rings if ts[-1] - t0 < 10 * self.p.onset_ring_tau_s]
        accel = f_world @ R_world_imu + self.accel_bias + self.rng.normal(0.0, self.accel_sigma, (n, 3))
        stamps = ts + self.rng.normal(0.0, self.p.timestamp_jitter_s, n) if self.p.timestamp_jitter_s else ts
        stamps = np.maximum.accumulate(stamps)
        try:
            self._fifo.put_nowait((stamps, gyro, accel))
            self.samples += n
        except queue.Full:
            self.dropped_chunks += 1

    def read(self, timeout: float = 0.05):
        """Next chunk (t (n,), gyro (n,3), accel (n,3)) or None after `timeout` seconds."""
        try:
            return self._fifo.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        pass
