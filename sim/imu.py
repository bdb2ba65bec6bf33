"""Simulated fingertip IMU (LSM6DSR in a soft fingertip): world kinematics in, timestamped SI samples out."""
from __future__ import annotations

import math
import queue
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import quat_to_matrix
from tecdard.drivers.lsm6dsr import Scaling
from tecdard.options import option, read_options
from tecdard.sim.rig import RigParams, RigSignal

GRAVITY_WORLD_M_S2 = np.array([0.0, 0.0, -9.81])
DEG = np.pi / 180.0
IIR_BLOCK = 64          # samples per closed-form block of the first-order lag (keeps a^-k well conditioned)
# The fingertip's apparent transmission against grip force (the paper: eta -> 1 as force grows; 2.0 at 30 N).
ETA_TRUE_TABLE = ((10.0, 3.2), (20.0, 2.5), (30.0, 2.0), (40.0, 1.7), (60.0, 1.4))
RING_REF_MASS_KG = 0.1


@dataclass
class SimImuParams:
    """The `sim.imu` section: the simulated fingertip and its LSM6DSR."""
    odr_hz: float = option(6667.0, "the IMU's data rate", unit="Hz", minval=100.0, maxval=20000.0)
    grip_force_n: float = option(30.0, "the grasp force: the true eta follows it (2.0 at 30 N)", unit="N",
                                 minval=0.0)
    eta: float | None = option(None, "a fixed true eta; none: from the grip force", kind="optfloat", above=0.0)
    lag_tau_s: float = option(0.003, "the fingertip's viscoelastic lag of the relative rotation", unit="s",
                              minval=0.0, maxval=0.1)
    gyro_noise_density: float = option(5e-3 * DEG, "gyro noise density (LSM6DSR: 5 mdps/sqrt(Hz))",
                                       unit="rad/s/sqrt(Hz)", minval=0.0)
    accel_noise_density: float = option(60e-6 * 9.81, "accelerometer noise density (LSM6DSR: 60 ug/sqrt(Hz))",
                                        unit="m/s^2/sqrt(Hz)", minval=0.0)
    gyro_bias_max: float = option(0.02, "per-axis initial gyro bias, drawn uniformly within +-", unit="rad/s",
                                  minval=0.0)
    accel_bias_max: float = option(0.05, "per-axis initial accelerometer bias, within +-", unit="m/s^2",
                                   minval=0.0)
    gyro_bias_walk: float = option(1e-4, "the gyro bias's random walk", unit="rad/s/sqrt(s)", minval=0.0)
    gyro_fs_dps: int = option(4000, "the gyro's full scale (int16 quantisation)", unit="dps")
    accel_fs_g: int = option(16, "the accelerometer's full scale (int16 quantisation)", unit="g")
    ring_per_m_s: float = option(100.0, "impact ring amplitude per TCP speed, for a 0.1 kg object",
                                 unit="(m/s^2)/(m/s)", minval=0.0)
    ring_hz: float = option(120.0, "the impact ring's frequency for a 0.1 kg object (scales with 1/sqrt(mass))",
                            unit="Hz", above=0.0)
    ring_tau_s: float = option(0.015, "the impact ring's decay time", unit="s", above=0.0)
    object_mass_kg: float = option(0.1, "the held object's mass", unit="kg", above=0.0)
    timestamp_jitter_s: float = option(2e-6, "the samples' timestamp jitter", unit="s", minval=0.0)
    imu_in_tcp_quat: tuple = option((0.0, 0.0, 0.0, 1.0), "the simulated IMU's true mount, (x, y, z, w), TCP <- "
                                                          "IMU (default: imu.imu_in_tcp_quat)", kind="quat")

    @classmethod
    def from_config(cls, section, default_mount=None) -> "SimImuParams":
        defaults = {} if default_mount is None else {"imu_in_tcp_quat": tuple(default_mount)}
        p = read_options(cls, section, defaults)
        try:
            Scaling(p.gyro_fs_dps, p.accel_fs_g)
        except ValueError as exc:
            key, _, problem = str(exc).partition(": ")
            raise section.error(key, problem) from None
        return p

    def true_eta(self) -> float:
        if self.eta is not None:
            return self.eta
        f, e = zip(*ETA_TRUE_TABLE)
        return float(np.interp(self.grip_force_n, f, e))


class FingertipSignal:
    """What the fingertip IMU reports for given kinematics (all world frame, per sample).

    gyro  = R_imu^T (w_tcp + lag((w_obj - w_tcp) / eta)) + bias(t) + noise   (then int16)
    accel = R_imu^T (a_tcp - g) + impact rings + bias + noise                 (then int16)
    The lag is the fingertip's first-order viscoelastic response; eta follows grip force;
    the gyro bias drifts as a random walk; noise follows the LSM6DSR densities at the ODR;
    outputs are quantised to the chip's int16 at the configured full scales.
    """

    def __init__(self, params: SimImuParams, seed: int = 0, rig: RigParams | None = None):
        self.params = params
        self.rng = np.random.default_rng(seed)
        # a real rig's disturbances (sim.rig), when asked for: they replace the bias and noise below, and
        # the signal is made with the mount and eta they put off their configured values
        self.rig = RigSignal(rig, params.odr_hz, seed) if rig is not None and rig.scale > 0.0 else None
        self.R_tcp_imu = quat_to_matrix(np.array(params.imu_in_tcp_quat))
        self.eta = params.true_eta()
        if self.rig is not None:
            self.R_tcp_imu = self.rig.true_mount(params.imu_in_tcp_quat)
            self.eta = self.rig.eta(self.eta)
        self.gyro_bias = self.rng.uniform(-params.gyro_bias_max, params.gyro_bias_max, 3)
        self.accel_bias = self.rng.uniform(-params.accel_bias_max, params.accel_bias_max, 3)
        nyquist = params.odr_hz / 2.0
        self.gyro_sigma = params.gyro_noise_density * math.sqrt(nyquist)
        self.accel_sigma = params.accel_noise_density * math.sqrt(nyquist)
        self.scaling = Scaling(params.gyro_fs_dps, params.accel_fs_g)
        self._lag_state = np.zeros(3)
        self._rings: list[tuple[float, np.ndarray, float]] = []   # (start, amplitude vector world, Hz)
        mass_ratio = RING_REF_MASS_KG / params.object_mass_kg
        self._ring_gain = params.ring_per_m_s * math.sqrt(mass_ratio)
        self._ring_hz = float(np.clip(params.ring_hz * math.sqrt(mass_ratio), 40.0, 400.0))

    def impact(self, t0: float, direction_world: np.ndarray, speed_m_s: float = 0.0,
               amplitude_m_s2: float | None = None) -> None:
        """Start a damped ring at t0. An impact's amplitude grows with speed and shrinks (and slows)
        with the held object's mass; a release (e.g. a hinge breaking away) gives its own amplitude."""
        amp = self._ring_gain * speed_m_s if amplitude_m_s2 is None else amplitude_m_s2
        self._rings.append((t0, amp * np.asarray(direction_world, float), self._ring_hz))

    def _lag(self, x: np.ndarray, dt: float) -> np.ndarray:
        """First-order low-pass (time constant lag_tau_s) of x (n, 3), state carried across calls."""
        if self.params.lag_tau_s <= 0:
            return x
        a = math.exp(-dt / self.params.lag_tau_s)
        out = np.empty_like(x)
        y0 = self._lag_state
        for k0 in range(0, len(x), IIR_BLOCK):
            blk = x[k0:k0 + IIR_BLOCK]
            m = len(blk)
            pw = a ** np.arange(1, m + 1)                          # a^(k+1)
            # y_k = a^(k+1) y0 + (1 - a) sum_j a^(k-j) x_j, in closed form for the block
            acc = np.cumsum(blk * (a ** -np.arange(m))[:, None], axis=0)
            y = pw[:, None] * y0 + (1 - a) * (a ** np.arange(m))[:, None] * acc
            out[k0:k0 + m] = y
            y0 = y[-1]
        self._lag_state = y0
        return out

    def sample(self, ts: np.ndarray, w_tcp: np.ndarray, w_obj: np.ndarray, a_tcp: np.ndarray,
               R_world_tcp: np.ndarray, v_tcp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(raw int16 (n, 6), gyro rad/s (n, 3), accel m/s^2 (n, 3)) at sample times ts; kinematics per sample
        (v_tcp: the TCP's velocity, for the rig's joint harmonics; None: at rest)."""
        n = len(ts)
        dt = 1.0 / self.params.odr_hz
        R_world_imu = R_world_tcp @ self.R_tcp_imu
        w_seen = w_tcp + self._lag((w_obj - w_tcp) / self.eta, dt)
        drift = np.cumsum(self.rng.normal(0.0, self.params.gyro_bias_walk * math.sqrt(dt), (n, 3)), axis=0)
        bias = self.gyro_bias + drift
        self.gyro_bias = bias[-1]
        gyro = w_seen @ R_world_imu
        if self.rig is None:
            gyro = gyro + bias + self.rng.normal(0.0, self.gyro_sigma, (n, 3))
        f_world = a_tcp - GRAVITY_WORLD_M_S2
        for t0, amp, hz in self._rings:
            s = ts - t0
            env = np.where(s >= 0, np.exp(-np.maximum(s, 0) / self.params.ring_tau_s)
                           * np.sin(2 * np.pi * hz * np.maximum(s, 0)), 0.0)
            f_world = f_world + env[:, None] * amp
        self._rings = [r for r in self._rings if ts[-1] - r[0] < 10 * self.params.ring_tau_s]
        accel = f_world @ R_world_imu
        if self.rig is not None:
            v = np.zeros((n, 3)) if v_tcp is None else v_tcp
            gyro, accel = self.rig.imu(ts, gyro, accel, a_tcp, v, w_tcp, R_world_imu)
            return self.rig.raw(gyro, accel), gyro, accel
        accel = accel + self.accel_bias + self.rng.normal(0.0, self.accel_sigma, (n, 3))
        raw = self.scaling.to_raw(gyro, accel)
        g, a = self.scaling.to_si(raw)
        return raw, g, a


class SimImu:
    """The simulated device. The physics thread calls `feed()` with each slice of kinematics.

    Without `wire`, `read()` hands the acquisition thread SI samples (t, gyro, accel) on the
    daemon's monotonic clock. With `wire` (sim.board's PyWire or FirmwareWire), the samples go to a
    board instead, which streams `tecdar-imu/1` to a pseudo-terminal, so the whole serial path
    (driver, parser, clock sync; with FirmwareWire the firmware too) runs in simulation.
    """

    def __init__(self, params: SimImuParams, seed: int = 0, fifo_chunks: int = 512, wire=None,
                 rig: RigParams | None = None):
        self.params = params
        self.signal = FingertipSignal(params, seed, rig)
        self.rng = np.random.default_rng(seed + 7)
        self.period = 1.0 / params.odr_hz
        self._next_t = None
        self._fifo: queue.Queue = queue.Queue(maxsize=fifo_chunks)
        self.wire = wire                 # sim.board.PyWire or FirmwareWire, or None
        self.dropped_chunks = 0
        self.samples = 0

    @property
    def R_tcp_imu(self) -> np.ndarray:
        return self.signal.R_tcp_imu

    def impact(self, t0: float, direction_world: np.ndarray, speed_m_s: float = 0.0,
               amplitude_m_s2: float | None = None) -> None:
        self.signal.impact(t0, direction_world, speed_m_s, amplitude_m_s2)

    def feed(self, t: np.ndarray, w_tcp: np.ndarray, w_obj: np.ndarray, a_tcp: np.ndarray,
             R_world_tcp: np.ndarray, v_tcp: np.ndarray | None = None) -> None:
        """Kinematic rows (m >= 2, world frame, e.g. 1 kHz) -> IMU samples for times up to t[-1]."""
        if self._next_t is None:
            self._next_t = float(t[0])
        n = int(np.floor((t[-1] - self._next_t) / self.period)) + 1
        if n <= 0:
            return
        ts = self._next_t + self.period * np.arange(n)
        self._next_t = float(ts[-1] + self.period)
        # Linear interpolation of all nine kinematic columns at once (np.interp per column cost
        # more than the physics step it served).
        ts_c = np.clip(ts, t[0], t[-1])
        j = np.clip(np.searchsorted(t, ts_c, side="right") - 1, 0, len(t) - 2)
        frac = ((ts_c - t[j]) / (t[j + 1] - t[j]))[:, None]
        v_tcp = np.zeros_like(a_tcp) if v_tcp is None else v_tcp
        kin = np.concatenate((w_tcp, w_obj, a_tcp, v_tcp), axis=1)
        kin = kin[j] + frac * (kin[j + 1] - kin[j])
        raw, gyro, accel = self.signal.sample(ts, kin[:, 0:3], kin[:, 3:6], kin[:, 6:9], R_world_tcp[-1],
                                              kin[:, 9:12])
        self.samples += n
        if self.wire is not None:
            self.wire.send(raw)                                    # never blocks the physics thread
            return
        stamps = ts + self.rng.normal(0.0, self.params.timestamp_jitter_s, n) if self.params.timestamp_jitter_s else ts
        if self.signal.rig is not None:
            stamps = self.signal.rig.stamps(stamps)       # the board's clock against the arm's
        stamps = np.maximum.accumulate(stamps)
        try:
            self._fifo.put_nowait((stamps, gyro, accel))
        except queue.Full:
            self.dropped_chunks += 1

    def read(self, timeout: float = 0.05):
        """Next chunk (t (n,), gyro (n,3), accel (n,3)) or None after `timeout` seconds."""
        try:
            return self._fifo.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        if self.wire is not None:
            self.wire.close()
