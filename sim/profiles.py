"""Free motion as real arms make it, written as recordings through the rig's disturbances (sim.rig):
what the onset trigger must never take for a contact.

Profiles (PROFILES), each with the proprioception its arm gives:
- `ur-cb3`, `ur-e`: speedL/speedJ trapezoids, the acceleration a step of 0.1-1.5 m/s^2 (1-3 rad/s^2 at
  the wrist), states at 125 Hz (CB3) and 500 Hz (e-Series), stamped on arrival 8 ms and 2 ms late;
- `franka`: jerk-limited motions (Ruckig at the FR3's Cartesian limits), states at 1 kHz, 1 ms late;
- `jtc`: a ROS 2 JointTrajectoryController's quintic splines through waypoints, `/joint_states` at
  100 Hz with 0.5 ms of stamp jitter, 4 ms late;
- `pendant`: an operator jogging: acceleration steps to a jog speed, held 0.2-2 s, released at once,
  reversals, on a CB3 (125 Hz, 8 ms).
Latency and jitter are scaled by the rig's `latency` and `jitter` levels like every disturbance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import matrix_to_quat, quat_to_matrix
from tecdard.sim.rig import RigParams, RigSignal

GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])
STEP_S = 1e-3                   # the arm's kinematics are made on this grid


@dataclass(frozen=True)
class Profile:
    kind: str                   # "trapezoid", "jerk", "spline", "jog"
    state_hz: float
    latency_s: float            # the states' stamps are this late (stamped on arrival)
    jitter_s: float             # the stamps' jitter, one sigma
    max_accel: float            # m/s^2, the largest acceleration (a step for trapezoid and jog)
    max_speed: float            # m/s
    max_alpha: float            # rad/s^2 at the wrist
    max_rate: float             # rad/s


PROFILES = {
    "ur-cb3": Profile("trapezoid", 125.0, 0.008, 0.0003, 1.5, 0.25, 3.0, 0.5),
    "ur-e": Profile("trapezoid", 500.0, 0.002, 0.0001, 1.5, 0.25, 3.0, 0.5),
    "franka": Profile("jerk", 1000.0, 0.001, 0.0001, 1.5, 0.25, 3.0, 0.5),
    "jtc": Profile("spline", 100.0, 0.004, 0.0005, 1.5, 0.25, 3.0, 0.5),
    "pendant": Profile("jog", 125.0, 0.008, 0.0003, 1.5, 0.25, 3.0, 0.5),
}


def _segments(profile: Profile, rng, duration_s: float) -> np.ndarray:
    """The arm's acceleration on the STEP_S grid (n, 4): x, y, z in m/s^2 and the wrist's about the
    tool axis in rad/s^2, as the profile makes it; rests, starts, stops and reversals."""
    n = int(duration_s / STEP_S)
    acc = np.zeros((n, 4))
    k = int(rng.uniform(0.3, 0.8) / STEP_S)
    while k < n:
        speed = rng.uniform(0.1, 1.0) * profile.max_speed
        a = rng.uniform(0.1, 1.0) * profile.max_accel
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        rate = rng.uniform(-1.0, 1.0) * profile.max_rate
        alpha = rng.uniform(0.3, 1.0) * profile.max_alpha
        hold = rng.uniform(0.2, 2.0) if profile.kind == "jog" else rng.uniform(0.05, 0.6)
        ramp = max(int(speed / a / STEP_S), 1)
        ramp_w = max(int(abs(rate) / alpha / STEP_S), 1)
        cruise = int(hold / STEP_S)
        total = 2 * max(ramp, ramp_w) + cruise
        if k + total >= n:
            break
        shape = _shape(profile.kind, ramp, cruise + 2 * max(ramp, ramp_w) - 2 * ramp)
        shape_w = _shape(profile.kind, ramp_w, total - 2 * ramp_w)
        acc[k:k + len(shape), :3] += np.outer(shape * a, d)
        acc[k:k + len(shape_w), 3] += shape_w * alpha * np.sign(rate)
        k += total
        reverse = rng.uniform() < 0.3          # a reversal: straight into the opposite move
        if not reverse:
            k += int(rng.uniform(0.1, 0.8) / STEP_S)
    return acc


def _shape(kind: str, ramp: int, cruise: int) -> np.ndarray:
    """The acceleration's shape over a move, in units of its peak: +1 for `ramp` steps, 0 for
    `cruise`, -1 for `ramp` (trapezoid, jog: steps); jerk-limited or spline: the same area, smooth."""
    if kind in ("trapezoid", "jog"):
        return np.concatenate([np.ones(ramp), np.zeros(cruise), -np.ones(ramp)])
    x = np.linspace(0.0, 1.0, ramp, endpoint=False) + 0.5 / ramp
    if kind == "jerk":                               # a sine-squared pulse: finite jerk, same area
        bump = 2.0 * np.sin(np.pi * x) ** 2
    else:                                            # a quintic spline's acceleration shape, same area
        bump = x ** 2 * (1 - x) ** 2
        bump = bump / np.mean(bump)
    return np.concatenate([bump, np.zeros(cruise), -bump])


def free_motion(profile_name: str, duration_s: float = 60.0, imu_hz: float = 6667.0, rig: RigParams | None = None,
                seed: int = 0, imu_in_tcp_quat=(0.0, 0.0, 0.0, 1.0), tcp_noise: float = 5e-5,
                tcp_vel_noise: float = 1e-3):
    """(recording fields, truth) of `duration_s` of free motion on profile `profile_name`, the IMU at
    `imu_hz` through the rig's disturbances (none: clean). Truth: the moves' accelerations' changes
    (`steps_t`), no contact."""
    profile = PROFILES[profile_name]
    rig = rig or RigParams()
    rng = np.random.default_rng(seed)
    acc4 = _segments(profile, rng, duration_s)
    t_k = np.arange(len(acc4)) * STEP_S
    vel4 = np.cumsum(acc4, axis=0) * STEP_S
    pos4 = np.cumsum(vel4, axis=0) * STEP_S
    p0 = np.array([0.5, 0.0, 0.3])
    # the IMU's samples (arm clock), the arm's kinematics held from the grid's step before each
    imu_t = np.arange(0.0, t_k[-1], 1.0 / imu_hz)
    j = np.minimum((imu_t / STEP_S).astype(int), len(t_k) - 1)
    a_w, v_w, yaw, yaw_rate = acc4[j, :3], vel4[j, :3], pos4[j, 3], vel4[j, 3]
    R_tcp = _yaw_down(yaw)
    signal = RigSignal(rig, imu_hz, seed)
    R_tcp_imu = signal.true_mount(imu_in_tcp_quat)
    R_world_imu = R_tcp @ R_tcp_imu
    w_world = np.outer(yaw_rate, [0.0, 0.0, 1.0])
    f_imu = np.einsum("nji,nj->ni", R_world_imu, a_w - GRAVITY_WORLD)
    w_imu = np.einsum("nji,nj->ni", R_world_imu, w_world)
    gyro, accel = _in_chunks(signal, imu_t, w_imu, f_imu, a_w, v_w, w_world, R_world_imu)
    # the states: measured on the arm's clock, stamped late and with jitter
    t_meas = np.arange(0.5 / profile.state_hz, t_k[-1], 1.0 / profile.state_hz)
    k = np.minimum((t_meas / STEP_S).astype(int), len(t_k) - 1)
    stamps = t_meas + profile.latency_s * rig.level("latency") \
        + rng.normal(0.0, profile.jitter_s * rig.level("jitter") + 1e-12, len(t_meas))
    stamps = np.maximum.accumulate(stamps + np.arange(len(stamps)) * 1e-9)
    fields = {
        "imu_t": signal.stamps(imu_t), "gyro": gyro, "accel": accel, "tcp_t": stamps,
        "tcp_pos": p0 + pos4[k, :3] + rng.normal(0.0, tcp_noise, (len(k), 3)),
        "tcp_quat": np.array([matrix_to_quat(R) for R in _yaw_down(pos4[k, 3])]),
        "tcp_vel": vel4[k, :3] + rng.normal(0.0, tcp_vel_noise, (len(k), 3)),
        "imu_in_tcp_quat": np.array(imu_in_tcp_quat, float) / np.linalg.norm(imu_in_tcp_quat),
        "meta": {"simulated": True, "kind": f"free-motion {profile_name}", "rig_scale": rig.scale,
                 "rig_only": rig.only, "seed": seed},
    }
    changes = np.flatnonzero(np.any(np.abs(np.diff(acc4, axis=0)) > 1e-9, axis=1)) * STEP_S
    truth = {"onset_t": np.array(np.nan), "kind": np.array("free-motion"), "steps_t": changes,
             "moving_s": np.array(float(np.count_nonzero(np.linalg.norm(vel4, axis=1) > 1e-4)) * STEP_S)}
    return fields, truth


def _in_chunks(signal: RigSignal, t, w_imu, f_imu, a_w, v_w, w_w, R, chunk: int = 1 << 16):
    gyro, accel = np.empty_like(w_imu), np.empty_like(f_imu)
    for s in range(0, len(t), chunk):
        e = s + chunk
        gyro[s:e], accel[s:e] = signal.imu(t[s:e], w_imu[s:e], f_imu[s:e], a_w[s:e], v_w[s:e], w_w[s:e], R[s:e])
    return gyro, accel


def _yaw_down(yaw: np.ndarray) -> np.ndarray:
    """The tool pointing down (x turned by pi), turned by yaw about world z: (n, 3, 3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R @ quat_to_matrix(np.array([1.0, 0.0, 0.0, 0.0]))
