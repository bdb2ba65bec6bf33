"""Recordings from real rigid-body physics (MuJoCo, the `bench` extra): a second source for the
estimation benchmark, with no signal model shared with sim/scenarios.py.

The world is the paper cutter. Its handle turns on a hinge with a stop at 0°, dry friction (its
breakaway rings the fingertip, as a real touch does) and viscous damping. The commanded path moves
a mocap target, as a stiff position-controlled arm moves its TCP.

The gripper is a 1 kg body held to the mocap target by a stiff weld, so it has real velocities and
accelerations (a mocap body's are zero, and its children's sensors would miss the arm's motion).
The fingertip is two compliant ball joints in series between the finger and the pad, with the
IMU's body between them. The pad is welded to the handle through a soft weld (the grasp), so the
IMU turns by a fraction of the handle's rotation relative to the gripper. That fraction is 1/eta,
set by the stiffness ratio, and it lags by `lag_tau_s` (the silicone's damping on the IMU body). MuJoCo's own gyro and
accelerometer sensors at the IMU's site (specific force: gravity included) give the signal, then
the LSM6DSR's noise densities, a turn-on bias and int16 quantisation at its full scales are added.

Motions (`motion`):
- `arc`: the TCP on the circle about the hinge, its orientation held (the fingertip twists);
- `arc-turning`: the same, the gripper turning with the handle (the daemon's arc following);
- `push`: a straight push along the handle's initial tangent. The grasp slides and stretches,
  and the handle follows as it can;
- `slip`: the arc with the gripper held, the grasp able to turn on the handle: once the
  fingertip's twist torque passes `slip_torque_nm` (dry friction in the grasp), the handle turns
  in the grasp and the fingertip's twist stops growing (the IMU no longer sees the handle turn);
- `circle` (the pen): its top circled about the vertical through the tip, the gripper held;
- `tilt` (the block): its top pushed on the arc about its bottom edge, which a ridge holds;
- `ongoing` (the block): the arm, moving from the recording's start and at `speed` after RAMP_S,
  slides the block along the table into the ridge (the onset, at `rest_s`, is that impact) and
  goes on, on the arc about the edge.
- `carry` (the block, lifted CARRY_LIFT_M clear of the table): no contact at all. After `rest_s`
  the arm moves it back and forth along x, each move a start (a half cosine of speed peaking at
  CARRY_ACCEL, the daemon's configured maximum), CARRY_CRUISE_S at `speed` and a stop, then
  CARRY_REST_S still: what the onset trigger must never fire on
  (truth's onset_t is NaN, its `moves` the moves' start and end times).

Proprioception is the mocap pose at `tcp_hz` with Gaussian position noise, and optionally the TCP
velocity with noise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import matrix_to_quat, rotvec_to_matrix

LSB_GYRO_RAD_S_PER_DPS = math.radians(1.0)
G = 9.80665


@dataclass
class MujocoScenario:
    motion: str = "arc"                # arc | arc-turning | push (the cutter); circle (the pen)
    radius: float = 0.12               # m, hinge to TCP
    speed: float = 0.02                # m/s, TCP
    eta: float = 2.0                   # the fingertip's transmission (stiffness ratio)
    lag_tau_s: float = 0.003           # the fingertip's viscoelastic time constant
    hinge_friction_nm: float = 0.05    # dry friction of the hinge (its breakaway rings the fingertip)
    imu_hz: float = 6667.0
    tcp_hz: float = 500.0
    tcp_noise: float = 5e-5            # m (encoder-grade; the paper's 5e-4)
    tcp_vel_noise: float = 1e-3        # m/s
    with_tcp_vel: bool = True
    gyro_noise_density: float = 8.7e-5     # rad/s/sqrt(Hz) (LSM6DSR: 5 mdps/sqrt(Hz))
    accel_noise_density: float = 5.9e-4   # m/s^2/sqrt(Hz) (60 ug/sqrt(Hz))
    gyro_bias_max: float = 0.02        # rad/s
    gyro_fs_dps: int = 4000
    accel_fs_g: int = 16
    rest_s: float = 0.5
    move_s: float = 1.5
    yaw_deg: float = 0.0               # the cutter's yaw about world z
    rig_scale: float = 0.0             # a real rig's disturbances (sim.rig) at this multiple; 0: the chip below
    rig_only: str = ""                 # ... only this one of them (sim.rig.DISTURBANCES)
    seed: int = 0

    circle_radius: float = 0.02        # m, the pen: the TCP's circle about the vertical through the tip
    slip_torque_nm: float = 0.05       # N m, `slip`: the grasp's dry friction about the handle (about 3 deg of handle at eta 2)

    @property
    def world(self) -> str:
        """The cutter on its hinge (line contact), a pen on its tip (point contact), or a block
        tipped up on its bottom edge against a ridge on the table (a line contact through real
        contacts: they may give and slide)."""
        return {"circle": "pen", "tilt": "block", "ongoing": "block", "carry": "block"}.get(self.motion, "cutter")

    def validate(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"motion: expected one of {', '.join(MOTIONS)}, got {self.motion!r}")
        if self.world == "block" and (self.yaw_deg != 0.0 or self.radius < 2 * BLOCK_HALF_WIDTH_M):
            raise ValueError(f"{self.motion}: the block's table lies along y (yaw_deg 0) and its lever is at least "
                             f"{2 * BLOCK_HALF_WIDTH_M:g} m")
        if self.motion == "slip" and not self.slip_torque_nm > 0.0:
            raise ValueError(f"slip_torque_nm: expected > 0, got {self.slip_torque_nm:g}")
        if self.motion == "circle" and not 0.005 <= self.circle_radius <= 0.5 * self.radius:
            raise ValueError(f"circle_radius: {self.circle_radius:g} is outside [0.005, radius / 2]")
        for name, lo, hi in (("radius", 0.02, 0.4), ("speed", 0.001, 0.2), ("eta", 1.01, 10.0),
                             ("imu_hz", 500.0, 20000.0), ("tcp_hz", 10.0, 2000.0), ("move_s", 0.2, 10.0)):
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise ValueError(f"{name}: {v:g} is outside [{lo:g}, {hi:g}]")


MOTIONS = ("arc", "arc-turning", "push", "slip", "circle", "tilt", "ongoing", "carry")
CARRY_LIFT_M = 0.05                        # `carry`: the block held this far above where it would stand
CARRY_CRUISE_S, CARRY_REST_S = 0.25, 0.25
CARRY_ACCEL = 0.5                          # m/s^2, `carry`'s peak acceleration (the configs' control.max_accel)
BLOCK_HALF_WIDTH_M = 0.03                  # the block: the TCP grasps its top, this far from the pivot edge in x
HINGE = np.array([0.40, 0.0, 0.30])        # the hinge point (the pen's tip), world (the robot base), m
RAMP_S = 0.05                              # the arm reaches its speed in this long
NOMINAL_GRIP_N = 30.0                      # meta.grip_force: the fingertip's eta is set directly, at this force
SETTLE_S = 0.3                             # simulated before the recording starts: the grasp takes the handle's weight


def _mjcf(sc: MujocoScenario, p_tcp: np.ndarray, R_tcp: np.ndarray, axis: np.ndarray,
          start: np.ndarray) -> tuple[str, float, str | None]:
    """The world: the gripper (mocap) and its two-stage fingertip, the cutter's handle on its hinge
    (or the pen, or the block). p_tcp: the TCP at the onset; the gripper and the block start
    `start` from there (`ongoing`)."""
    # series torsional springs: the IMU body turns by kB/(kA+kB) = 1/eta of the pad's turn. The
    # silicone's viscosity holds the IMU body back (a damper to the finger, none to the pad): it
    # follows the pad's twist as a first-order lag of dA/(kA+kB) = lag_tau_s (Kelvin-Voigt)
    k_a = 2.0                                              # N m/rad, finger -> IMU body
    k_b = k_a / (sc.eta - 1.0)                             # N m/rad, IMU body -> pad
    d_a, d_b = (k_a + k_b) * sc.lag_tau_s, 1e-4 * k_b
    q = matrix_to_quat(R_tcp)                              # (x, y, z, w) -> MuJoCo's (w, x, y, z)
    quat = f"{q[3]} {q[0]} {q[1]} {q[2]}"
    handle_dir = p_tcp - HINGE
    L = float(np.linalg.norm(handle_dir))
    mid = HINGE + 0.5 * handle_dir
    if sc.world == "pen":       # the tip in a dimple: a ball joint, with the same friction and damping
        joint = f'<joint name="hinge" type="ball" damping="0.02" frictionloss="{sc.hinge_friction_nm}"/>'
    else:
        joint = (f'<joint name="hinge" type="hinge" axis="{axis[0]} {axis[1]} {axis[2]}" range="-100 0" '
                 f'limited="true" damping="0.02" frictionloss="{sc.hinge_friction_nm}"/>')
    held = f"""<body name="handle" pos="{HINGE[0]} {HINGE[1]} {HINGE[2]}">
      {joint}
      <geom type="capsule" fromto="0 0 0 {handle_dir[0]} {handle_dir[1]} {handle_dir[2]}" size="0.008"
            contype="0" conaffinity="0" mass="0.1"/>
    </body>"""
    anchor = handle_dir
    if sc.world == "block":     # a box on the table, its bottom edge at HINGE against a ridge (world x-z plane)
        h2 = 0.5 * handle_dir[2]
        c = HINGE + np.array([BLOCK_HALF_WIDTH_M, 0.0, h2])
        c = c + start
        # `ongoing` slides the block on the table: a slick table (the ridge holds the edge), or the
        # block stick-slips and rocks in the grasp on its way
        mu = 0.05 if sc.motion == "ongoing" else 0.8
        held = f"""<geom name="table" type="box" pos="{HINGE[0]} 0 {HINGE[2] - 0.01}" size="0.3 0.3 0.01" friction="{mu}"/>
    <geom name="ridge" type="box" pos="{HINGE[0] - 0.004} 0 {HINGE[2] + 0.004}" size="0.004 0.3 0.004"/>
    <body name="handle" pos="{c[0]} {c[1]} {c[2]}">
      <freejoint name="hinge"/>
      <geom type="box" size="{BLOCK_HALF_WIDTH_M} 0.04 {h2}" mass="0.3" friction="{mu}"/>
    </body>"""
        anchor = np.array([0.0, 0.0, h2])
    # `slip`: the grasp turns on the handle against dry friction (the pad's contact, a ball joint).
    # MuJoCo's friction loss is a soft constraint scaled by the dof's inverse inertia: on the tiny
    # contact body alone it held nothing; the armature gives the dof the inertia of a real contact
    # patch's (with 1e-3 it sticks until the twist torque reaches slip_torque_nm, then slides)
    grasp, grasped = "", "pad"
    if sc.motion == "slip":
        grasp = f"""
          <body name="grasp" pos="0 0 0">
            <joint name="grasp" type="ball" frictionloss="{sc.slip_torque_nm}" damping="{1e-3 * k_b}"
                   armature="1e-3"/>
            <geom type="sphere" size="0.004" contype="0" conaffinity="0" mass="0.002"/>
          </body>"""
        grasped = "grasp"
    p_start = p_tcp + start
    return f"""
<mujoco model="tecdar-cutter">
  <option timestep="{1.0 / sc.imu_hz}" gravity="0 0 -{G}" integrator="implicitfast"/>
  <worldbody>
    <body name="target" mocap="true" pos="{p_start[0]} {p_start[1]} {p_start[2]}" quat="{quat}"/>
    <body name="gripper" pos="{p_start[0]} {p_start[1]} {p_start[2]}" quat="{quat}">
      <freejoint name="arm"/>
      <geom type="box" size="0.02 0.04 0.02" contype="0" conaffinity="0" mass="1.0"/>
      <body name="imu_body" pos="0 0 0">
        <joint name="tip_a" type="ball" stiffness="{k_a}" damping="{d_a}"/>
        <geom type="sphere" size="0.006" contype="0" conaffinity="0" mass="0.004"/>
        <site name="imu" pos="0 0 0"/>
        <body name="pad" pos="0 0 0">
          <joint name="tip_b" type="ball" stiffness="{k_b}" damping="{d_b}"/>
          <geom type="sphere" size="0.006" contype="0" conaffinity="0" mass="0.004"/>{grasp}
        </body>
      </body>
    </body>
    {held}
  </worldbody>
  <equality>
    <weld body1="target" body2="gripper" relpose="0 0 0 1 0 0 0" solref="0.001 1" torquescale="100"/>
    <weld body1="{grasped}" body2="handle" anchor="{anchor[0]} {anchor[1]} {anchor[2]}"
          relpose="0 0 0 0 0 0 0" solref="0.002 1" torquescale="100"/>
  </equality>
  <sensor>
    <gyro site="imu" name="gyro"/>
    <accelerometer site="imu" name="accel"/>
  </sensor>
</mujoco>
""", L, mid


def generate(sc: MujocoScenario) -> tuple[dict, dict]:
    """(recording fields, truth) as sim.scenarios.generate gives them."""
    import mujoco
    sc.validate()
    rng = np.random.default_rng(sc.seed)
    path = _Path(sc)
    xml, L, _ = _mjcf(sc, path.p0, path.R0, path.axis, path.start)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)        # the weld holds the pad where the model starts it: at the grasp
    for _ in range(int(SETTLE_S / model.opt.timestep)):
        mujoco.mj_step(model, data)       # gravity loads the grasp and the fingertip: not part of the recording
    dt = model.opt.timestep
    n_rest, n_move = int(sc.rest_s / dt), int(sc.move_s / dt)
    t = np.arange(n_rest + n_move) * dt
    gyro, accel, p_cmd, R_cmd, v_cmd, angle = _simulate(mujoco, model, data, sc, path, t)
    if sc.rig_scale > 0:
        gyro, accel, t_imu = _rig(sc, t, gyro, accel, v_cmd, R_cmd)
    else:
        gyro, accel, t_imu = (*_chip(sc, rng, gyro, accel), t)
    # proprioception at its own rate
    tcp_t = np.arange(0.3 / sc.tcp_hz, t[-1], 1.0 / sc.tcp_hz)
    idx = np.clip(np.searchsorted(t, tcp_t), 0, len(t) - 1)
    fields = {
        "imu_t": t_imu, "gyro": gyro, "accel": accel, "tcp_t": t[idx],
        "tcp_pos": p_cmd[idx] + rng.normal(0.0, sc.tcp_noise, (len(idx), 3)),
        "tcp_quat": np.array([matrix_to_quat(R) for R in R_cmd[idx]]),
        "imu_in_tcp_quat": np.array([0.0, 0.0, 0.0, 1.0]),
        "grip_force": None,
        "tcp_vel": (v_cmd[idx] + rng.normal(0.0, sc.tcp_vel_noise, (len(idx), 3))) if sc.with_tcp_vel else None,
        "plane_normal": None,
        "meta": {"simulated": True, "engine": f"mujoco {mujoco.__version__}", "kind": f"mujoco-{sc.motion}",
                 "radius": L, "speed": sc.speed, "eta_true": sc.eta, "seed": sc.seed,
                 "grip_force": NOMINAL_GRIP_N, "fingertip_lag_s": sc.lag_tau_s},
    }
    # the onset: the arm starts to push the held handle (the handle itself may stick a little longer)
    point = sc.world == "pen"
    if sc.motion == "carry":
        return fields, {"onset_t": np.array(np.nan), "kind": np.array("free-air"), "moves": np.array(path.moves(t[-1]))}
    truth = {"p_c": HINGE.copy(), "axis": np.zeros(3) if point else path.axis, "onset_t": np.array(t[n_rest]),
             "onset_stamp_t": np.array(t_imu[n_rest]),     # the board's stamp of the contact's instant
             "kind": np.array("point-circle" if point else "edge-arc"), "radius": np.array(L),
             "eta": np.array(sc.eta), "angle_t": t, "angle": angle - angle[0]}
    return fields, truth


class _Path:
    """The commanded TCP path of a scenario: where it starts (p0, R0, the world's start offset), the
    hinge axis, and where the mocap target is at each time (`at`)."""

    def __init__(self, sc: MujocoScenario):
        self.sc = sc
        self.Rz = rotvec_to_matrix(np.array([0.0, 0.0, math.radians(sc.yaw_deg)]))
        self.axis = self.Rz @ np.array([0.0, 1.0, 0.0])            # the hinge axis, horizontal
        out_dir = self.Rz @ np.array([1.0, 0.0, 0.0])              # the handle lies along +x (yawed) from the hinge
        if sc.world == "pen":       # tilted from the vertical through the tip by the circle's radius
            h = math.sqrt(sc.radius ** 2 - sc.circle_radius ** 2)
            self.p0 = HINGE + sc.circle_radius * out_dir + np.array([0.0, 0.0, h])
        elif sc.world == "block":   # the top's middle, above the block's middle
            h = math.sqrt(sc.radius ** 2 - BLOCK_HALF_WIDTH_M ** 2)
            self.p0 = HINGE + BLOCK_HALF_WIDTH_M * out_dir + np.array([0.0, 0.0, h])
            out_dir = (self.p0 - HINGE) / sc.radius       # the lever arm's direction, for the tangent below
        else:
            self.p0 = HINGE + sc.radius * out_dir
        self.R0 = self.Rz @ np.diag([1.0, -1.0, -1.0])             # tool down
        # `ongoing`: the block and the gripper start along +x (away from the ridge) as far as the arm
        # travels from the start to the onset
        self.approach = sc.speed * (sc.rest_s - 0.5 * RAMP_S) if sc.motion == "ongoing" else 0.0
        self.start = np.array([self.approach, 0.0, CARRY_LIFT_M if sc.motion == "carry" else 0.0])
        self.tangent0 = np.cross(self.axis, out_dir)              # the handle's tangent at the grasp (rising)
        if self.tangent0[2] < 0:
            self.tangent0 = -self.tangent0
        self.sign = 1.0 if np.dot(np.cross(out_dir, self.tangent0), self.axis) > 0 else -1.0

    def distance(self, t: np.ndarray) -> np.ndarray:
        """The path length commanded at times t: the TCP's speed rises as a half cosine over RAMP_S (peak
        acceleration speed * pi / (2 RAMP_S), 0.63 m/s^2 at 20 mm/s), then holds (`ongoing`: from the
        start, negative before the impact: the slide towards the ridge)."""
        sc = self.sc
        if sc.motion == "carry":
            return self._carry(t)
        t_go = 0.0 if sc.motion == "ongoing" else sc.rest_s
        s_move = np.maximum(t - t_go, 0.0)
        dist = np.where(s_move < RAMP_S,
                        0.5 * sc.speed * (s_move - RAMP_S / math.pi * np.sin(math.pi * s_move / RAMP_S)),
                        0.5 * sc.speed * RAMP_S + sc.speed * (s_move - RAMP_S))
        return dist - self.approach if sc.motion == "ongoing" else dist

    @property
    def carry_ramp_s(self) -> float:
        """`carry`'s start and stop: a half cosine of speed whose peak acceleration is CARRY_ACCEL."""
        return max(RAMP_S, self.sc.speed * math.pi / (2.0 * CARRY_ACCEL))

    def moves(self, t_end: float) -> list[tuple[float, float]]:
        """`carry`: each move's (start, end) time up to t_end."""
        span = 2 * self.carry_ramp_s + CARRY_CRUISE_S
        starts = np.arange(self.sc.rest_s, t_end - span - CARRY_REST_S, span + CARRY_REST_S)
        return [(float(t0), float(t0 + span)) for t0 in starts]

    def _carry(self, t: np.ndarray) -> np.ndarray:
        """The signed distance along x at times t: moves out and back (see the module's `carry`)."""
        sc, ramp = self.sc, self.carry_ramp_s
        v = np.zeros(len(t))
        for k, (t0, t1) in enumerate(self.moves(float(t[-1]) + 1.0)):
            up = np.clip((t - t0) / ramp, 0.0, 1.0)
            down = np.clip((t1 - t) / ramp, 0.0, 1.0)
            shape = 0.5 * (1 - np.cos(np.pi * np.minimum(up, down)))
            v += np.where((t >= t0) & (t <= t1), (1.0 if k % 2 == 0 else -1.0) * sc.speed * shape, 0.0)
        return np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])

    def at(self, dist: float) -> tuple[np.ndarray, np.ndarray]:
        """(p, R) of the mocap target `dist` along the path."""
        sc = self.sc
        if sc.motion == "carry":
            return self.p0 + self.start + dist * np.array([1.0, 0.0, 0.0]), self.R0
        if sc.motion == "push":
            return self.p0 + dist * self.tangent0, self.R0
        if sc.motion == "circle":       # about the vertical through the tip, the gripper held
            psi = dist / sc.circle_radius
            p = HINGE + self.Rz @ np.array([sc.circle_radius * math.cos(psi), sc.circle_radius * math.sin(psi),
                                            0.0]) + np.array([0.0, 0.0, self.p0[2] - HINGE[2]])
            return p, self.R0
        if sc.motion == "ongoing" and dist < 0.0:    # sliding into the ridge, along -x
            return self.p0 - dist * np.array([1.0, 0.0, 0.0]), self.R0
        theta = self.sign * dist / sc.radius
        Rt = rotvec_to_matrix(self.axis * theta)
        return HINGE + Rt @ (self.p0 - HINGE), (Rt @ self.R0 if sc.motion == "arc-turning" else self.R0)


def _simulate(mujoco, model, data, sc: MujocoScenario, path: _Path, t: np.ndarray):
    """Step the model along the path: (gyro, accel, p_tcp, R_tcp, v_tcp, object angle) at each step. The
    arm's TCP is what its encoders would give: the gripper body's own pose and velocity, behind the
    target (world-aligned, at the body's origin)."""
    n = len(t)
    dist = path.distance(t)
    gyro, accel = np.empty((n, 3)), np.empty((n, 3))
    p_cmd, R_cmd, v_cmd = np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3))
    angle = np.empty(n)
    gid, aid = model.sensor("gyro").adr[0], model.sensor("accel").adr[0]
    hinge_q = model.joint("hinge").qposadr[0]
    mocap = model.body("target").mocapid[0]
    gripper = model.body("gripper").id
    vel6 = np.zeros(6)
    for k in range(n):
        p, R = path.at(dist[k])
        data.mocap_pos[mocap] = p
        data.mocap_quat[mocap] = np.roll(matrix_to_quat(R), 1)
        mujoco.mj_step(model, data)
        gyro[k] = data.sensordata[gid:gid + 3]
        accel[k] = data.sensordata[aid:aid + 3]
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, gripper, vel6, 0)
        p_cmd[k], R_cmd[k], v_cmd[k] = data.xpos[gripper], data.xmat[gripper].reshape(3, 3), vel6[3:]
        if sc.world in ("pen", "block"):
            q = data.qpos[hinge_q + (3 if sc.world == "block" else 0):][:4]
            angle[k] = 2.0 * math.atan2(float(np.linalg.norm(q[1:])), abs(float(q[0])))
        else:
            angle[k] = data.qpos[hinge_q]
    return gyro, accel, p_cmd, R_cmd, v_cmd, angle


def _rig(sc: MujocoScenario, t, gyro, accel, v_cmd, R_cmd):
    """A real rig's disturbances (sim.rig) on MuJoCo's clean IMU: the mount's error as the readings
    turned by it, the arm's vibration from the commanded motion, the sensor, the board's clock."""
    from tecdard.sim.rig import RigParams, RigSignal
    rig = RigSignal(RigParams().at(sc.rig_scale, sc.rig_only), sc.imu_hz, sc.seed)
    R_err = rig.true_mount((0.0, 0.0, 0.0, 1.0))
    a_world = np.gradient(v_cmd, t, axis=0)
    R_world_imu = R_cmd @ R_err
    gyro, accel = rig.imu(t, gyro @ R_err, accel @ R_err, a_world, v_cmd, np.zeros_like(v_cmd), R_world_imu)
    return gyro, accel, rig.stamps(t)


def _chip(sc: MujocoScenario, rng, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The LSM6DSR: white noise at its densities, a turn-on bias, int16 at the full scales."""
    n = len(gyro)
    g_lsb = sc.gyro_fs_dps * LSB_GYRO_RAD_S_PER_DPS / 32768.0
    a_lsb = sc.accel_fs_g * G / 32768.0
    gyro = gyro + rng.uniform(-sc.gyro_bias_max, sc.gyro_bias_max, 3) \
        + rng.normal(0.0, sc.gyro_noise_density * math.sqrt(sc.imu_hz / 2.0), (n, 3))
    accel = accel + rng.normal(0.0, sc.accel_noise_density * math.sqrt(sc.imu_hz / 2.0), (n, 3))
    return (np.clip(np.round(gyro / g_lsb), -32768, 32767) * g_lsb,
            np.clip(np.round(accel / a_lsb), -32768, 32767) * a_lsb)
