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


COMMAND_LATENCY_S = 0.002     # free_motion's commands take effect this late ...
COMMAND_NOISE = 5e-4          # ... with the servo's corrections on each (m/s, rad/s), as sim.scenarios'


def free_motion(profile_name: str, duration_s: float = 60.0, imu_hz: float = 6667.0, rig: RigParams | None = None,
                seed: int = 0, imu_in_tcp_quat=(0.0, 0.0, 0.0, 1.0), tcp_noise: float = 5e-5,
                tcp_vel_noise: float = 1e-3, command_tick_s: float = 0.0):
    """(recording fields, truth) of `duration_s` of free motion on profile `profile_name`, the IMU at
    `imu_hz` through the rig's disturbances (none: clean). Truth: the moves' accelerations' changes
    (`steps_t`), no contact. `command_tick_s` > 0: the daemon commanded the motion (live_cmd: every
    tick, the rates the arm was to reach by the next, as sim.scenarios' Cartesian arm's, and the yaw's)."""
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
    at = [np.interp(t_meas, t_k, pos4[:, i]) for i in range(4)]       # the arm where each state was measured
    vel_at = np.column_stack([np.interp(t_meas, t_k, vel4[:, i]) for i in range(3)])
    stamps = _stamped(t_meas, profile.latency_s * rig.level("latency"), profile.jitter_s * rig.level("jitter"),
                      profile.state_hz, rng)
    fields = {
        "imu_t": signal.stamps(imu_t), "gyro": gyro, "accel": accel, "tcp_t": stamps,
        "tcp_pos": p0 + np.column_stack(at[:3]) + rng.normal(0.0, tcp_noise, (len(t_meas), 3)),
        "tcp_quat": np.array([matrix_to_quat(R) for R in _yaw_down(at[3])]),
        "tcp_vel": vel_at + rng.normal(0.0, tcp_vel_noise, (len(t_meas), 3)),
        "imu_in_tcp_quat": np.array(imu_in_tcp_quat, float) / np.linalg.norm(imu_in_tcp_quat),
        "meta": {"simulated": True, "kind": f"free-motion {profile_name}", "rig_scale": rig.scale,
                 "rig_only": rig.only, "seed": seed},
    }
    if command_tick_s > 0.0:
        # as a velocity interface (speedJ) is told: the rates to reach by the next tick's command
        tk = np.arange(0.0, t_k[-1] - COMMAND_LATENCY_S, command_tick_s)
        k = np.minimum(((tk + COMMAND_LATENCY_S + command_tick_s) / STEP_S).astype(int), len(t_k) - 1)
        noise = np.random.default_rng(seed + 1).normal(0.0, COMMAND_NOISE, (len(tk), 4))
        fields["live_cmd"] = np.column_stack([tk, vel4[k] + noise])
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


def wrist_calibration(profile_name: str = "ur-e", imu_hz: float = 6667.0, rig: RigParams | None = None,
                      seed: int = 0, amplitude_deg: float = 10.0, speed_deg_s: float = 5.0,
                      imu_in_tcp_quat=(0.0, 0.0, 0.0, 1.0), ramp_s: float = 0.05):
    """(recording fields, truth) of the wrist turned about each TCP axis in turn, +amplitude, -2
    amplitude, +amplitude at speed_deg_s (ramps of ramp_s), the TCP still: what `tecdard calibrate-mount
    --live` records. The recording states the configured mount; truth holds the one the signal was
    made with (`R_tcp_imu`) and the clock offset between the IMU's stamps and the states'."""
    profile = PROFILES[profile_name]
    rig = rig or RigParams()
    rng = np.random.default_rng(seed)
    w = np.radians(speed_deg_s)
    seg = np.radians(amplitude_deg) / w                      # s per amplitude
    rates = []
    for axis in range(3):
        for sign, length in ((1, seg), (-1, 2 * seg), (1, seg)):
            n = int(length / STEP_S)
            ramp = np.minimum(1.0, np.minimum(np.arange(n), n - np.arange(n)) * STEP_S / ramp_s)
            r = np.zeros((n, 3))
            r[:, axis] = sign * w * ramp
            rates.append(r)
        rates.append(np.zeros((int(0.3 / STEP_S), 3)))
    rest = np.zeros((int(0.5 / STEP_S), 3))
    w_body = np.vstack([rest, *rates, rest])
    n = len(w_body)
    t_k = np.arange(n) * STEP_S
    R0 = quat_to_matrix(np.array([1.0, 0.0, 0.0, 0.0]))
    R = np.empty((n, 3, 3))
    R[0] = R0
    for k in range(1, n):                                     # body rates integrated (exact per step)
        R[k] = R[k - 1] @ _exp(w_body[k - 1] * STEP_S)
    imu_t = np.arange(0.0, t_k[-1], 1.0 / imu_hz)
    j = np.minimum((imu_t / STEP_S).astype(int), n - 1)
    signal = RigSignal(rig, imu_hz, seed)
    R_tcp_imu = signal.true_mount(imu_in_tcp_quat)
    R_world_imu = R[j] @ R_tcp_imu
    w_world = np.einsum("nij,nj->ni", R[j], w_body[j])
    zeros = np.zeros((len(j), 3))
    f_imu = np.einsum("nji,nj->ni", R_world_imu, np.broadcast_to(-GRAVITY_WORLD, (len(j), 3)))
    w_imu = np.einsum("nji,nj->ni", R_world_imu, w_world)
    gyro, accel = _in_chunks(signal, imu_t, w_imu, f_imu, zeros, zeros, w_world, R_world_imu)
    t_meas = np.arange(0.5 / profile.state_hz, t_k[-1], 1.0 / profile.state_hz)
    k = np.minimum((t_meas / STEP_S).astype(int), n - 1)
    # the attitude at each measurement: the step's start turned on by its body rate for the remainder
    R_meas = np.array([R[kk] @ _exp(w_body[kk] * (tm - kk * STEP_S)) for kk, tm in zip(k, t_meas)])
    latency = profile.latency_s * rig.level("latency")
    stamps = _stamped(t_meas, latency, profile.jitter_s * rig.level("jitter"), profile.state_hz, rng)
    imu_stamps = signal.stamps(imu_t)
    fields = {
        "imu_t": imu_stamps, "gyro": gyro, "accel": accel, "tcp_t": stamps,
        "tcp_pos": np.tile([0.5, 0.0, 0.3], (len(k), 1)) + rng.normal(0.0, 5e-5, (len(k), 3)),
        "tcp_quat": np.array([matrix_to_quat(Rk) for Rk in R_meas]),
        "tcp_vel": rng.normal(0.0, 1e-3, (len(k), 3)),
        "imu_in_tcp_quat": np.array(imu_in_tcp_quat, float) / np.linalg.norm(imu_in_tcp_quat),
        "meta": {"simulated": True, "kind": "wrist-calibration", "rig_scale": rig.scale, "seed": seed},
    }
    # the same instant: the IMU stamps it t + clock, the states t + latency
    clock = float(imu_stamps[len(imu_stamps) // 2] - imu_t[len(imu_t) // 2])
    truth = {"R_tcp_imu": R_tcp_imu, "offset_s": np.array(clock - latency), "kind": np.array("wrist-calibration"),
             "onset_t": np.array(np.nan)}
    return fields, truth


def _exp(v: np.ndarray) -> np.ndarray:
    from tecdard.control.geometry import rotvec_to_matrix
    return rotvec_to_matrix(v)


def _stamped(t_meas: np.ndarray, latency_s: float, jitter_s: float, state_hz: float, rng) -> np.ndarray:
    """The states' stamps: measured at t_meas, stamped latency_s later with Gaussian jitter, clipped to
    +-0.4 of a period so that the stamps keep their order (a receiver stamps in arrival order)."""
    jitter = np.clip(rng.normal(0.0, jitter_s + 1e-12, len(t_meas)), -0.4 / state_hz, 0.4 / state_hz)
    return t_meas + latency_s + jitter
