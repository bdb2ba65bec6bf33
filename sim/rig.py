"""What a real rig does to the signal: one disturbance layer for the signal model (sim.scenarios,
sim.profiles), MuJoCo (sim.mujoco_source) and the daemon's simulated board (sim.imu).

Each disturbance is a named parameter of `RigParams` with its nominal value (the level a real rig
has) and the source of that value in docs/simulator.md; `scale` multiplies every one of them at
once (0: the clean signal, 1: nominal, 3: thrice), and `only` keeps one of them for the robustness
matrix (benchmarks/robustness.py). Groups:

- the sensor (ST DS12544, the LSM6DSR): noise densities, turn-on bias, bias instability, bias and
  sensitivity drift as the fingertip warms, scale and cross-axis errors, int16 quantisation and
  saturation at the full scales;
- the arm's own vibration, which its joint encoders do not see: lightly damped structural modes rung
  by every change of the arm's acceleration, joint motor and gear harmonics tied to the joints'
  speeds, a standing servo dither at rest, the gripper's motor;
- the clocks: the board's offset and drift against the arm's;
- the grasp: the mount's rotation off its configured value, the fingertip's compliance (eta).

The motion profiles (UR trapezoids, Franka, a ROS 2 trajectory controller, a pendant jog) and the
proprioception's rate, latency and jitter are sim.profiles'.

Streaming: `RigSignal.imu` keeps its state (modes, phases, bias walks, the warming clock) across
calls, so the daemon's board feeds it chunk by chunk and a recording in one call, alike.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from tecdard.control.geometry import quat_to_matrix, rotvec_to_matrix
from tecdard.drivers.lsm6dsr import Scaling
from tecdard.options import option, read_options

DEG = math.pi / 180.0
G = 9.81
BLOCK = 64                 # samples per closed-form block of a complex one-pole (keeps p^-k conditioned)
# The joint speeds that ring the gear harmonics, from the TCP's motion: the signal model has no arm,
# so each of three "joint groups" turns at the TCP's speed over JOINT_LEVER_M plus its rate, with a
# fixed share; a stand-in for the Jacobian (stated in docs/simulator.md).
JOINT_LEVER_M = 0.5
JOINT_SHARES = (1.0, 0.7, 0.4)
HARMONIC_REF_RAD_S = 0.2   # joint speed at which a harmonic reaches its full amplitude


@dataclass(frozen=True)
class RigParams:
    """The `sim.rig` section: the disturbances of a real rig, at `scale` times their nominal values
    (docs/simulator.md gives each one's source)."""
    scale: float = option(0.0, "every disturbance at this multiple of its nominal value (0: the clean signal)",
                          minval=0.0, maxval=10.0)
    only: str = option("", "keep only this disturbance (a field name below; empty: all)", max_len=64)
    # -- the sensor (DS12544, typical values)
    gyro_noise_density: float = option(5e-3 * DEG, "gyro rate noise density (DS12544: 5 mdps/sqrt(Hz))",
                                       unit="rad/s/sqrt(Hz)", minval=0.0)
    accel_noise_density: float = option(60e-6 * G, "accelerometer noise density (DS12544: 60 ug/sqrt(Hz))",
                                        unit="m/s^2/sqrt(Hz)", minval=0.0)
    gyro_turn_on_bias: float = option(1.0 * DEG, "gyro zero-rate level per axis, drawn within +- (DS12544: "
                                                 "+-1 dps)", unit="rad/s", minval=0.0)
    accel_turn_on_bias: float = option(10e-3 * G, "accelerometer zero-g level per axis, within +- (DS12544: "
                                                   "+-10 mg)", unit="m/s^2", minval=0.0)
    gyro_bias_instability: float = option(3.0 * DEG / 3600.0 * 60.0, "the gyro bias's wander (a first-order "
                                          "Gauss-Markov process with bias_tau_s; not in DS12544: chosen)",
                                          unit="rad/s", minval=0.0)
    bias_tau_s: float = option(100.0, "the bias wander's correlation time", unit="s", above=0.0)
    warm_k: float = option(6.0, "how far the fingertip warms after power-on (no source: chosen)", unit="K",
                           minval=0.0)
    warm_tau_s: float = option(120.0, "the warming's time constant (no source: chosen)", unit="s", above=0.0)
    gyro_bias_tempco: float = option(0.01 * DEG, "gyro zero-rate change per kelvin (DS12544: +-0.01 dps/K)",
                                     unit="rad/s/K", minval=0.0)
    accel_bias_tempco: float = option(0.1e-3 * G, "zero-g change per kelvin (DS12544: +-0.1 mg/K)",
                                      unit="m/s^2/K", minval=0.0)
    sensitivity_tempco: float = option(0.0001, "sensitivity change per kelvin (DS12544: +-0.007-0.01 %/K)",
                                       unit="1/K", minval=0.0)
    scale_error: float = option(0.01, "per-axis sensitivity error, within +- (DS12544: +-1 %)", minval=0.0)
    cross_axis: float = option(0.01, "cross-axis sensitivity, within +- (not in DS12544: 1 %, a MEMS "
                                     "package's usual)", minval=0.0)
    gyro_fs_dps: int = option(4000, "the gyro's full scale: int16 quantisation and saturation", unit="dps")
    accel_fs_g: int = option(16, "the accelerometer's full scale", unit="g")
    # -- the arm's own vibration (what its encoders do not see)
    mode_hz: tuple = option((14.0, 33.0), "the arm's structural modes at the tool", unit="Hz", minval=1.0)
    mode_damping: float = option(0.03, "the modes' damping ratio (lightly damped)", minval=0.001, maxval=0.7)
    mode_gain: float = option(0.3, "the tool's ring per m/s^2 of a change of the arm's acceleration, per mode",
                              minval=0.0)
    vibration_lever_m: float = option(0.08, "from the tool's vibration centre to the IMU: accel = rate x "
                                            "2 pi f x lever", unit="m", above=0.0)
    harmonic_rad_s: float = option(0.04, "gyro amplitude of each joint group's gear harmonic at full speed "
                                         "(a real arm's tool: 0.045-0.07 rad/s moving)", unit="rad/s",
                                   minval=0.0)
    gear_ratio: float = option(101.0, "the joints' strain-wave gear ratio (2 harmonics per wave-generator turn)",
                               above=0.0)
    rest_dither_rad_s: float = option(0.015, "the servo dither with the arm still (a real arm's tool: 0.015 "
                                             "rad/s)", unit="rad/s", minval=0.0)
    rest_dither_hz: float = option(40.0, "the dither's centre frequency (no source: chosen)", unit="Hz",
                                   above=0.0)
    gripper_motor_m_s2: float = option(0.05, "the gripper motor's line at the IMU (no source: chosen)",
                                       unit="m/s^2", minval=0.0)
    gripper_motor_hz: float = option(180.0, "the gripper motor's line frequency", unit="Hz", above=0.0)
    # -- clocks
    clock_offset_s: float = option(0.001, "the board's clock ahead of the arm's after sync", unit="s",
                                   minval=-1.0, maxval=1.0)
    clock_drift_ppm: float = option(30.0, "the board's clock drift against the arm's (a crystal's +-30 ppm)",
                                    unit="ppm", minval=-1000.0, maxval=1000.0)
    # -- the grasp
    mount_error_deg: float = option(5.0, "the IMU's mount off its configured rotation", unit="deg", minval=0.0,
                                    maxval=90.0)
    eta_error: float = option(0.1, "the fingertip's compliance off its calibration (relative, within +-)",
                              minval=0.0, maxval=0.9)

    @classmethod
    def from_config(cls, section) -> "RigParams":
        p = read_options(cls, section)
        if p.only and p.only not in DISTURBANCES:
            raise section.error("only", f"expected one of {', '.join(DISTURBANCES)}, got {p.only!r}")
        return p

    def level(self, name: str) -> float:
        """The multiple of its nominal value that disturbance `name` takes."""
        if self.only and name != self.only:
            return 0.0
        return self.scale

    def at(self, scale: float, only: str = "") -> "RigParams":
        return replace(self, scale=float(scale), only=only)


# The disturbances `only` may name: each is one group of RigParams fields, scaled together.
DISTURBANCES = {
    "noise": ("gyro_noise_density", "accel_noise_density"),
    "turn_on_bias": ("gyro_turn_on_bias", "accel_turn_on_bias"),
    "bias_instability": ("gyro_bias_instability",),
    "warming": ("warm_k",),
    "scale_cross": ("scale_error", "cross_axis"),
    "modes": ("mode_gain",),
    "harmonics": ("harmonic_rad_s",),
    "dither": ("rest_dither_rad_s",),
    "gripper_motor": ("gripper_motor_m_s2",),
    "clock": ("clock_offset_s", "clock_drift_ppm"),
    "mount": ("mount_error_deg",),
    "eta": ("eta_error",),
    # the motion profile's own: sim.profiles reads these levels
    "latency": (),
    "jitter": (),
}
assert all(f in {x.name for x in fields(RigParams)} for group in DISTURBANCES.values() for f in group)


def _one_pole(x: np.ndarray, p: complex, y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y_k = p y_{k-1} + x_k for complex p (|p| < 1), x (n, m): in closed form per BLOCK samples.
    Returns (y (n, m) complex, the last y)."""
    out = np.empty(x.shape, dtype=complex)
    for k0 in range(0, len(x), BLOCK):
        blk = x[k0:k0 + BLOCK]
        m = len(blk)
        powers = p ** np.arange(m)
        acc = np.cumsum(blk * (1.0 / powers)[:, None], axis=0)
        y = powers[:, None] * (p * y0 + acc)
        out[k0:k0 + m] = y
        y0 = y[-1]
    return out, y0


def _unit_rows(rng, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


class RigSignal:
    """The rig's disturbances on one fingertip IMU at `odr_hz`, streaming. `imu()` takes the clean
    specific force and rate (IMU frame) with the arm's own motion (world) and returns what the chip
    reports; `stamps()` the board's timestamps; `true_mount()` the mount the signal is made with."""

    def __init__(self, params: RigParams, odr_hz: float, seed: int = 0):
        self.p = params
        self.odr_hz = float(odr_hz)
        self.dt = 1.0 / self.odr_hz
        rng = np.random.default_rng(seed + 4801)
        self.rng = rng
        lv = params.level
        self.gyro_bias = rng.uniform(-1, 1, 3) * params.gyro_turn_on_bias * lv("turn_on_bias")
        self.accel_bias = rng.uniform(-1, 1, 3) * params.accel_turn_on_bias * lv("turn_on_bias")
        self.gm = np.zeros(3)                          # the bias wander's state
        self.sign_g, self.sign_a = rng.choice([-1.0, 1.0], 3), rng.choice([-1.0, 1.0], 3)
        self.sens_sign = rng.choice([-1.0, 1.0])

        def matrix() -> np.ndarray:
            M = np.eye(3) + np.diag(rng.uniform(-1, 1, 3) * params.scale_error * lv("scale_cross"))
            off = rng.uniform(-1, 1, (3, 3)) * params.cross_axis * lv("scale_cross")
            return M + off - np.diag(np.diag(off))
        self.M_gyro, self.M_accel = matrix(), matrix()
        nyquist = self.odr_hz / 2.0
        self.gyro_sigma = params.gyro_noise_density * math.sqrt(nyquist) * lv("noise")
        self.accel_sigma = params.accel_noise_density * math.sqrt(nyquist) * lv("noise")
        self.scaling = Scaling(params.gyro_fs_dps, params.accel_fs_g)
        # modes: a complex pole each, rung by the arm's acceleration changes
        self.modes = []
        for hz in params.mode_hz:
            if hz >= nyquist:
                continue
            w = 2 * math.pi * hz
            z = params.mode_damping
            pole = complex(math.exp(-z * w * self.dt) * math.cos(w * math.sqrt(1 - z * z) * self.dt),
                           math.exp(-z * w * self.dt) * math.sin(w * math.sqrt(1 - z * z) * self.dt))
            self.modes.append((w, pole, np.zeros(3, dtype=complex), _unit_rows(rng, 1)[0]))
        self.mode_gain = params.mode_gain * lv("modes")
        self._a_prev = None
        # the dither: a narrow-band process about rest_dither_hz (a complex pole driven by white noise)
        w = 2 * math.pi * min(params.rest_dither_hz, 0.45 * self.odr_hz)
        r = math.exp(-0.15 * w * self.dt)
        self.dither_pole = complex(r * math.cos(w * self.dt), r * math.sin(w * self.dt))
        self.dither_w = w
        self.dither_gain = params.rest_dither_rad_s * lv("dither") * math.sqrt(2 * (1 - r * r))
        self.dither_state = np.zeros(3, dtype=complex)
        self.joint_axes = _unit_rows(rng, len(JOINT_SHARES))
        self.joint_phase = rng.uniform(0, 2 * math.pi, len(JOINT_SHARES))
        self.harmonic = params.harmonic_rad_s * lv("harmonics")
        self.gripper = params.gripper_motor_m_s2 * lv("gripper_motor")
        self.gripper_axis = _unit_rows(rng, 1)[0]
        self.t0 = None                                   # the board's power-on (the warming starts there)
        self._clock_t0 = None                            # the clocks' sync (the drift starts there)

    # -- the grasp
    def true_mount(self, configured_quat) -> np.ndarray:
        """The rotation TCP <- IMU the signal is made with: the configured one turned by mount_error_deg
        (x level) about a fixed random axis (the config then is off by that much)."""
        R = quat_to_matrix(np.asarray(configured_quat, float))
        err = self.p.mount_error_deg * self.p.level("mount") * DEG
        if err == 0.0:
            return R
        axis = _unit_rows(np.random.default_rng(int(self.rng.integers(1 << 30))), 1)[0]
        return R @ rotvec_to_matrix(axis * err)

    def eta(self, eta_true: float) -> float:
        """The fingertip's transmission off its calibration by eta_error (x level), a fixed draw."""
        e = self.p.eta_error * self.p.level("eta")
        return float(eta_true * (1.0 + np.random.default_rng(int(self.rng.integers(1 << 30))).uniform(-e, e)))

    # -- the clocks
    def stamps(self, t: np.ndarray) -> np.ndarray:
        """The board's stamps, on the arm's clock, of samples taken at arm-clock times t: offset, and
        drifting from the first sample stamped on (the sync at power-on)."""
        lv = self.p.level("clock")
        if self._clock_t0 is None:
            self._clock_t0 = float(t[0])
        return t + self.p.clock_offset_s * lv + self.p.clock_drift_ppm * 1e-6 * lv * (t - self._clock_t0)

    # -- the signal
    def imu(self, t: np.ndarray, w_imu: np.ndarray, f_imu: np.ndarray, a_world: np.ndarray,
            v_world: np.ndarray, w_world: np.ndarray, R_world_imu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gyro rad/s, accel m/s^2) (n, 3) as the chip reports them at times t (n,), from the clean rate
        and specific force in the IMU frame and the arm's own acceleration, velocity and rate (world,
        (n, 3)); R_world_imu (3, 3) or (n, 3, 3)."""
        n = len(t)
        if self.t0 is None:
            self.t0 = float(t[0])
        gyro_vib, accel_vib = self._vibration(t, a_world, v_world, w_world)
        R = np.broadcast_to(R_world_imu, (n, 3, 3))
        gyro = w_imu + np.einsum("nji,nj->ni", R, gyro_vib)
        accel = f_imu + np.einsum("nji,nj->ni", R, accel_vib)
        # warming: the biases and sensitivities move with the fingertip's temperature
        dT = self.p.warm_k * self.p.level("warming") * (1.0 - np.exp(-(t - self.t0) / self.p.warm_tau_s))
        sens = 1.0 + self.sens_sign * self.p.sensitivity_tempco * dT
        gyro = (gyro @ self.M_gyro.T) * sens[:, None]
        accel = (accel @ self.M_accel.T) * sens[:, None]
        gyro += self.gyro_bias + self._wander(n) + np.outer(dT, self.sign_g * self.p.gyro_bias_tempco)
        accel += self.accel_bias + np.outer(dT, self.sign_a * self.p.accel_bias_tempco)
        gyro += self.rng.normal(0.0, self.gyro_sigma, (n, 3)) if self.gyro_sigma else 0.0
        accel += self.rng.normal(0.0, self.accel_sigma, (n, 3)) if self.accel_sigma else 0.0
        raw = self.scaling.to_raw(gyro, accel)
        return self.scaling.to_si(raw)

    def raw(self, gyro: np.ndarray, accel: np.ndarray) -> np.ndarray:
        return self.scaling.to_raw(gyro, accel)

    def _wander(self, n: int) -> np.ndarray:
        """The gyro bias's first-order Gauss-Markov wander (n, 3), rad/s."""
        sigma = self.p.gyro_bias_instability * self.p.level("bias_instability")
        if sigma == 0.0:
            return np.zeros((n, 3))
        a = math.exp(-self.dt / self.p.bias_tau_s)
        drive = self.rng.normal(0.0, sigma * math.sqrt(1 - a * a), (n, 3))
        y, self.gm = _one_pole(drive, complex(a, 0.0), self.gm.astype(complex))
        self.gm = self.gm.real
        return y.real

    def _vibration(self, t, a_world, v_world, w_world) -> tuple[np.ndarray, np.ndarray]:
        """The arm's vibration at the tool, world: (rate (n, 3) rad/s, acceleration (n, 3) m/s^2)."""
        n = len(t)
        rate = np.zeros((n, 3))
        acc = np.zeros((n, 3))
        lever = self.p.vibration_lever_m
        if self.mode_gain and self.modes:
            prev = a_world[0] if self._a_prev is None else self._a_prev
            da = np.diff(a_world, axis=0, prepend=prev[None, :])
            self._a_prev = a_world[-1].copy()
            for i, (w, pole, y0, axis) in enumerate(self.modes):
                y, y_last = _one_pole(da.astype(complex), pole, y0)
                self.modes[i] = (w, pole, y_last, axis)
                ring = -self.mode_gain * y.real                # the tool lags the arm's change, then rings
                acc += ring
                rate += np.cross(axis, -self.mode_gain * y.imag) / (w * lever)
        if self.dither_gain:
            drive = self.rng.normal(0.0, 1.0, (n, 3)) * self.dither_gain
            y, self.dither_state = _one_pole(drive.astype(complex), self.dither_pole, self.dither_state)
            rate += y.real
            acc += np.cross(self.joint_axes[0], y.imag) * self.dither_w * lever
        if self.harmonic:
            speed = np.linalg.norm(v_world, axis=1) / JOINT_LEVER_M + np.linalg.norm(w_world, axis=1)
            for j, share in enumerate(JOINT_SHARES):
                qd = share * speed
                w_h = 2.0 * self.p.gear_ratio * qd                       # rad/s of the harmonic
                phase = self.joint_phase[j] + np.cumsum(w_h * self.dt)
                self.joint_phase[j] = float(phase[-1]) % (2 * math.pi)
                amp = self.harmonic * np.minimum(qd / HARMONIC_REF_RAD_S, 1.0)
                rate += np.outer(amp * np.sin(phase), self.joint_axes[j])
                acc += np.cross(self.joint_axes[j], np.outer(amp * w_h * lever * np.cos(phase), np.ones(3))
                                * self.joint_axes[(j + 1) % len(JOINT_SHARES)])
        if self.gripper and self.p.gripper_motor_hz < 0.5 * self.odr_hz:
            acc += np.outer(self.gripper * np.sin(2 * math.pi * self.p.gripper_motor_hz * t), self.gripper_axis)
        return rate, acc
