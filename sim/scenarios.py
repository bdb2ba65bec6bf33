"""Simulated contact scenarios written as recordings: the paper's line, point and hinge contacts, vectorised."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tecdard.control.geometry import matrix_to_quat, quat_to_matrix, rotvec_to_matrix, unit
from tecdard.sim.rig import RigParams, RigSignal

KINDS = ("edge-arc", "edge-translate", "edge-ongoing", "point-circle", "hinge")
GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])
RAMP_S = 0.05            # the TCP speed ramps up over this long (cosine) when starting from rest
# The fingertip's apparent transmission against grip force (true curve): eta -> 1 with force.
ETA_TRUE_TABLE = ((10.0, 3.2), (20.0, 2.5), (30.0, 2.0), (40.0, 1.7), (60.0, 1.4))


@dataclass
class Scenario:
    kind: str = "edge-arc"
    radius: float = 0.12              # m, TCP to contact (point contact: tool length)
    speed: float = 0.02               # m/s, TCP
    duration_s: float = 1.0           # s after onset
    rest_s: float = 0.5               # s at rest before onset (ongoing: approach time)
    circle_radius: float = 0.02       # m, point-circle: TCP circle radius
    imu_hz: float = 6667.0
    tcp_hz: float = 65.0
    grip_force: float = 30.0          # N
    eta: float | None = None          # true eta; None: from ETA_TRUE_TABLE at grip_force
    gyro_noise: float = 5e-3          # rad/s per sample (LSM6DSR at 6.7 kHz)
    accel_noise: float = 0.034        # m/s^2 per sample
    gyro_bias: float = 0.02           # rad/s, per-axis bias drawn in +-
    tcp_noise: float = 5e-5           # m, TCP position noise (encoder grade)
    tcp_vel_noise: float = 1e-3       # m/s, reported TCP velocity noise
    with_tcp_vel: bool = True
    planar: bool = True               # write plane_normal for line contacts
    tool_tilt_deg: float = 0.0        # TCP orientation tilted about the contact axis
    tcp_rotates: bool | None = None   # gripper turns with the object (default: hinge only)
    imu_in_tcp_quat: tuple = (0.0, 0.0, 0.0, 1.0)
    contact: tuple = (0.5, 0.0, 0.2)  # world, m
    axis: tuple = (0.0, 1.0, 0.0)     # contact line / hinge axis, world
    start_dir: tuple = (0.0, 0.0, 1.0)  # from contact to TCP at onset, world
    ring_gain: float = 100.0          # impact ring amplitude per TCP speed, (m/s^2)/(m/s)
    ring_hz: float = 120.0
    ring_tau_s: float = 0.015
    timestamp_jitter_s: float = 2e-6
    rig_scale: float = 0.0            # a real rig's disturbances (sim.rig) at this multiple; 0: the noise above
    rig_only: str = ""                # ... only this one of them (sim.rig.DISTURBANCES)
    tcp_latency_s: float = 0.0        # the states stamped this late (on arrival), at rig_scale 1
    command_tick_s: float = 0.0       # the daemon drives the arm: its ticks' commands in live_cmd (0: none)
    command_latency_s: float = 0.002  # ... each takes effect this late
    command_noise: float = 5e-4       # m/s, the servo's corrections on each tick's command (its feedback)
    seed: int = 0
    extra: dict = field(default_factory=dict)

    def true_eta(self) -> float:
        if self.eta is not None:
            return self.eta
        f, e = zip(*ETA_TRUE_TABLE)
        return float(np.interp(self.grip_force, f, e))


def _rot(axis: np.ndarray, angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v (n, 3) or (3,) about unit axis by angle (n,) (Rodrigues, vectorised)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    v = np.broadcast_to(v, (len(angle), 3))
    return v * c + np.cross(axis, v) * s + np.outer(np.ones(len(angle)), axis) * (v @ axis)[:, None] * (1 - c)


def _ramp_distance(t: np.ndarray, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Path length and speed from rest with a cosine speed ramp over RAMP_S, t >= 0."""
    tt = np.maximum(t, 0.0)
    in_ramp = tt < RAMP_S
    v = np.where(in_ramp, speed * 0.5 * (1 - np.cos(np.pi * tt / RAMP_S)), speed)
    s_ramp = speed * 0.5 * (tt - RAMP_S / np.pi * np.sin(np.pi * tt / RAMP_S))
    s = np.where(in_ramp, s_ramp, speed * 0.5 * RAMP_S + speed * (tt - RAMP_S))
    return s, v


def _imu(sc: Scenario, rng, t, s_time, t0_dir, acc, v, w_tcp, w_obj, R_tcp):
    """The fingertip IMU's (gyro, accel, stamps, the rig's signal or None) for the kinematics: the
    LSM6DSR's noise and bias, or (rig_scale) a real rig's disturbances (sim.rig)."""
    n, eta, after = len(t), sc.true_eta(), s_time >= 0
    rig = RigSignal(RigParams().at(sc.rig_scale, sc.rig_only), sc.imu_hz, sc.seed) if sc.rig_scale > 0 else None
    R_tcp_imu = quat_to_matrix(np.array(sc.imu_in_tcp_quat, float)) if rig is None else rig.true_mount(
        sc.imu_in_tcp_quat)
    eta_signal = eta if rig is None else rig.eta(eta)
    R_world_imu = R_tcp @ R_tcp_imu
    w_seen = w_tcp + (w_obj - w_tcp) / eta_signal
    gyro = np.einsum("nji,nj->ni", R_world_imu, w_seen)
    f_world = acc - GRAVITY_WORLD
    ring = np.where(after, np.exp(-np.maximum(s_time, 0) / sc.ring_tau_s)
                    * np.sin(2 * np.pi * sc.ring_hz * np.maximum(s_time, 0)), 0.0)
    f_world = f_world + (sc.ring_gain * sc.speed) * ring[:, None] * t0_dir
    accel = np.einsum("nji,nj->ni", R_world_imu, f_world)
    if rig is None:
        gyro += rng.uniform(-sc.gyro_bias, sc.gyro_bias, 3) + rng.normal(0, sc.gyro_noise, (n, 3))
        accel += rng.normal(0, sc.accel_noise, (n, 3))
    else:
        gyro, accel = rig.imu(t, gyro, accel, acc, v, w_tcp, R_world_imu)
    imu_t = t + rng.normal(0, sc.timestamp_jitter_s, n)
    imu_t = np.maximum.accumulate(imu_t + np.arange(n) * 1e-12)
    if rig is not None:
        imu_t = rig.stamps(imu_t)

    return gyro, accel, imu_t, rig


def _commands(sc: Scenario, rng, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """live_cmd's rows for a daemon that drives the arm along the scenario's path: each tick's time and the
    rates it commanded, those of a Cartesian arm (three prismatic joints, m/s, world axes: the signal
    model has no joints): the TCP's velocity to reach by the next tick (a velocity interface's target, as
    speedJ's), with the servo's corrections."""
    tk = np.arange(t[0], t[-1] - sc.command_latency_s, sc.command_tick_s)
    idx = np.clip(np.searchsorted(t, tk + sc.command_latency_s + sc.command_tick_s), 0, len(t) - 1)
    return np.column_stack([tk, v[idx] + rng.normal(0.0, sc.command_noise, (len(tk), 3))])


def generate(sc: Scenario):
    """Returns (recording fields dict, truth dict) for `tecdard.recording.save_recording`."""
    if sc.kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}")
    rng = np.random.default_rng(sc.seed)
    a = unit(np.array(sc.axis, float), "axis")
    u0 = np.array(sc.start_dir, float)
    u0 = unit(u0 - np.dot(u0, a) * a, "start_dir")
    t0_dir = np.cross(a, u0)                      # initial tangential (probing) direction
    c = np.array(sc.contact, float)
    L = sc.radius
    t_on = sc.rest_s
    n = int(round((sc.rest_s + sc.duration_s) * sc.imu_hz))
    t = np.arange(n) / sc.imu_hz
    s_time = t - t_on
    after = s_time >= 0
    R0 = rotvec_to_matrix(a * np.radians(sc.tool_tilt_deg)) @ rotvec_to_matrix(np.array([np.pi, 0, 0]))
    rotates = sc.tcp_rotates if sc.tcp_rotates is not None else sc.kind == "hinge"

    if sc.kind in ("edge-arc", "hinge"):
        s, v_mag = _ramp_distance(s_time, sc.speed)
        phi = np.where(after, s / L, 0.0)
        phid = np.where(after, v_mag / L, 0.0)
        p = c + _rot(a, phi, L * u0)
        w_obj = phid[:, None] * a
        obj_angle = phi
        truth_p = c
    elif sc.kind in ("edge-translate", "edge-ongoing"):
        if sc.kind == "edge-ongoing":
            s = sc.speed * s_time                   # moving at constant speed before and after impact
            v_mag = np.full(n, sc.speed)
        else:
            s, v_mag = _ramp_distance(s_time, sc.speed)
        s = np.where(after, s, np.minimum(s, 0.0))
        p = c + L * u0 + s[:, None] * t0_dir
        theta = np.where(after, np.arctan2(np.maximum(s, 0), L), 0.0)
        thetad = np.where(after, v_mag * L / (L ** 2 + np.maximum(s, 0) ** 2), 0.0)
        w_obj = thetad[:, None] * a
        obj_angle = theta
        truth_p = c
    else:  # point-circle: tool of length L pivoting about its tip, TCP on a horizontal circle
        ar = sc.circle_radius
        h = np.sqrt(L ** 2 - ar ** 2)
        s, v_mag = _ramp_distance(s_time, sc.speed)
        psi = np.where(after, s / ar, 0.0)
        psid = np.where(after, v_mag / ar, 0.0)
        d = np.stack([ar * np.cos(psi), ar * np.sin(psi), np.full(n, h)], axis=1) / L
        dd = np.stack([-ar * np.sin(psi), ar * np.cos(psi), np.zeros(n)], axis=1) * (psid / L)[:, None]
        p = c + L * d
        w_obj = np.cross(d, dd)
        obj_angle = np.arccos(np.clip(d @ d[0], -1, 1))
        truth_p = c
        a = np.zeros(3)
    v = np.gradient(p, t, axis=0)
    acc = np.gradient(v, t, axis=0)
    if rotates and sc.kind != "point-circle":
        w_tcp = w_obj.copy()
        R_tcp = np.einsum("nij,jk->nik", np.stack([rotvec_to_matrix(a * ang) for ang in obj_angle]), R0)
    else:
        w_tcp = np.zeros((n, 3))
        R_tcp = np.broadcast_to(R0, (n, 3, 3))
    eta = sc.true_eta()
    gyro, accel, imu_t, rig = _imu(sc, rng, t, s_time, t0_dir, acc, v, w_tcp, w_obj, R_tcp)

    # Proprioception at its own rate, on the same clock.
    tcp_t = np.arange(0.0, t[-1], 1.0 / sc.tcp_hz) + 0.3 / sc.tcp_hz
    idx = np.clip(np.searchsorted(t, tcp_t), 0, n - 1)
    tcp_pos = p[idx] + rng.normal(0, sc.tcp_noise, (len(idx), 3))
    tcp_quat = np.array([matrix_to_quat(R) for R in R_tcp[idx]])
    latency = sc.tcp_latency_s * (rig.p.level("latency") if rig is not None else 1.0)
    fields = {
        "imu_t": imu_t, "gyro": gyro, "accel": accel, "tcp_t": t[idx] + latency, "tcp_pos": tcp_pos,
        "tcp_quat": tcp_quat,
        "imu_in_tcp_quat": np.array(sc.imu_in_tcp_quat, float) / np.linalg.norm(sc.imu_in_tcp_quat),
        "grip_force": np.full(len(idx), sc.grip_force),
        "tcp_vel": (v[idx] + rng.normal(0, sc.tcp_vel_noise, (len(idx), 3))) if sc.with_tcp_vel else None,
        "plane_normal": a if (sc.planar and sc.kind != "point-circle") else None,
        "meta": {"simulated": True, "kind": sc.kind, "radius": L, "speed": sc.speed, "grip_force": sc.grip_force,
                 "eta_true": eta, "seed": sc.seed},
    }
    if sc.command_tick_s > 0.0:
        fields["live_cmd"] = _commands(sc, rng, t, v)
    truth = {"p_c": truth_p, "axis": a, "onset_t": np.array(t_on), "kind": np.array(sc.kind),
             # the board's stamp of the contact's instant (its clock's offset and drift, sim.rig)
             "onset_stamp_t": np.array(t_on if rig is None else float(rig.stamps(np.array([t_on]))[0])),
             "radius": np.array(L), "eta": np.array(eta), "angle_t": t, "angle": obj_angle}
    return fields, truth


@dataclass
class FreeAirMoves:
    """The arm carrying the tool through the air, touching nothing: jerk-limited starts and stops
    (Ruckig, the daemon's own planner's limits) along random directions, the tool turning about the
    TCP's z as it goes, with rests between. What the onset trigger must never take for a contact."""
    moves: int = 10
    max_speed: float = 0.1            # m/s per axis
    max_accel: float = 0.5            # m/s^2 per axis (configs' control.max_accel)
    max_jerk: float = 5.0             # m/s^3 per axis (control.max_jerk)
    max_rate: float = 0.5             # rad/s, the tool turning
    max_alpha: float = 2.0            # rad/s^2
    reach: float = 0.1                # m, targets within this of the start per axis
    rest_s: tuple = (0.2, 0.5)        # s, the rest before each move (uniform)
    imu_hz: float = 6667.0
    tcp_hz: float = 500.0
    gyro_noise: float = 5e-3          # rad/s per sample
    accel_noise: float = 0.034        # m/s^2 per sample
    gyro_bias: float = 0.02
    accel_bias: float = 0.05
    tcp_noise: float = 5e-5
    tcp_vel_noise: float = 1e-3
    imu_in_tcp_quat: tuple = (0.0, 0.0, 0.0, 1.0)
    seed: int = 0


def free_air(sc: FreeAirMoves):
    """(recording fields, truth) of `sc`: truth holds the moves' start and end times (no contact)."""
    import ruckig
    rng = np.random.default_rng(sc.seed)
    step = 1e-3
    otg, inp, out = ruckig.Ruckig(4, step), ruckig.InputParameter(4), ruckig.OutputParameter(4)
    inp.max_velocity = [sc.max_speed] * 3 + [sc.max_rate]
    inp.max_acceleration = [sc.max_accel] * 3 + [sc.max_alpha]
    inp.max_jerk = [sc.max_jerk] * 3 + [10.0 * sc.max_alpha]
    x = np.zeros(4)
    rows, moves = [], []
    t = 0.0
    for _ in range(sc.moves):
        for _ in range(int(rng.uniform(*sc.rest_s) / step)):
            rows.append(np.concatenate([[t], x, np.zeros(8)]))
            t += step
        inp.current_position, inp.current_velocity, inp.current_acceleration = x.tolist(), [0.0] * 4, [0.0] * 4
        inp.target_position = np.concatenate([rng.uniform(-sc.reach, sc.reach, 3),
                                              [rng.uniform(-0.5, 0.5)]]).tolist()
        inp.target_velocity, inp.target_acceleration = [0.0] * 4, [0.0] * 4
        t_start = t
        while True:
            res = otg.update(inp, out)
            rows.append(np.concatenate([[t], out.new_position, out.new_velocity, out.new_acceleration]))
            t += step
            out.pass_to_input(inp)
            if res == ruckig.Result.Finished:
                break
        x = np.array(out.new_position)
        moves.append((t_start, t))
    for _ in range(int(sc.rest_s[1] / step)):
        rows.append(np.concatenate([[t], x, np.zeros(8)]))
        t += step
    k = np.array(rows)
    imu_t = np.arange(0.0, k[-1, 0], 1.0 / sc.imu_hz)
    col = [np.interp(imu_t, k[:, 0], k[:, i]) for i in range(1, 13)]
    p0 = np.array([0.5, 0.0, 0.3])
    p = p0 + np.column_stack(col[0:3])
    yaw, yaw_rate = col[3], col[7]
    acc = np.column_stack(col[8:11])
    R0 = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))             # the tool pointing down
    z = np.array([0.0, 0.0, 1.0])
    c, s_ = np.cos(yaw), np.sin(yaw)
    Rz = np.zeros((len(yaw), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s_, s_, c, 1.0
    R_tcp = Rz @ R0
    R_world_imu = R_tcp @ quat_to_matrix(np.array(sc.imu_in_tcp_quat, float))
    w_world = yaw_rate[:, None] * z
    n = len(imu_t)
    gyro = np.einsum("nji,nj->ni", R_world_imu, w_world) + rng.uniform(-sc.gyro_bias, sc.gyro_bias, 3) \
        + rng.normal(0.0, sc.gyro_noise, (n, 3))
    accel = np.einsum("nji,nj->ni", R_world_imu, acc - GRAVITY_WORLD) + rng.uniform(-sc.accel_bias, sc.accel_bias, 3) \
        + rng.normal(0.0, sc.accel_noise, (n, 3))
    tcp_t = np.arange(0.3 / sc.tcp_hz, imu_t[-1], 1.0 / sc.tcp_hz)
    idx = np.searchsorted(imu_t, tcp_t)
    vel = np.column_stack([np.interp(tcp_t, k[:, 0], k[:, i]) for i in (5, 6, 7)])
    fields = {
        "imu_t": imu_t, "gyro": gyro, "accel": accel, "tcp_t": tcp_t,
        "tcp_pos": p[idx] + rng.normal(0.0, sc.tcp_noise, (len(idx), 3)),
        "tcp_quat": np.array([matrix_to_quat(R) for R in R_tcp[idx]]),
        "tcp_vel": vel + rng.normal(0.0, sc.tcp_vel_noise, (len(idx), 3)),
        "imu_in_tcp_quat": np.array(sc.imu_in_tcp_quat, float) / np.linalg.norm(sc.imu_in_tcp_quat),
        "meta": {"simulated": True, "kind": "free-air", "moves": sc.moves, "seed": sc.seed},
    }
    truth = {"moves": np.array(moves), "onset_t": np.array(np.nan), "kind": np.array("free-air")}
    return fields, truth
