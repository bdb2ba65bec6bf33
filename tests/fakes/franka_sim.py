"""franky-sim for the Franka backend's tests: libfranka's own protocol over MuJoCo physics, on loopback.

`python -m tests.fakes.franka_sim --host 127.0.0.x` runs franky-sim's server (PyPI franky-sim, the
`franka-sim` extra) with one FR3 and its hand, on that address (the robot's port 1337 and the
hand's 1338 are fixed, so each server gets an address of its own), and prints `READY <host>` once
it listens. The simulation steps on an absolute 1 kHz schedule (franky-sim's own loop sleeps a
fixed 1 ms after each step's work and runs at 0.7-0.9x real time on 2 cores). Steps that fall
behind catch up at once, so the simulated clock (the robot's and the fingertip board's) keeps to
the wall clock as a real robot's and board's do; only a stall of over a second restarts the
schedule. To keep that schedule on 2 cores shared with the daemon and franky, the simulator takes
a real-time priority where the host allows it (`READY <host> SCHED_FIFO`, else `nice-10` or
`normal`), and the scene's truth is written on a thread of its own.

Options for the tests:
- `--reply-version N` / `--reply-status incompatible`: the robot server answers libfranka's
  Connect with this version, or with franka's "incompatible library version" status;
- `--silent`: a server that accepts the connection and never answers (what an older libfranka
  meets, and franky.Robot() then waits for ever);
- `--joint7-kv`: joint 7's velocity gain (franky-sim's default 200 makes it chatter);
- `--control FILE`: `reflex` written there raises libfranka's joint_reflex error in the robot's
  state (franky-sim simulates none) until the robot's automatic error recovery clears it; `reflex-stuck`
  holds the robot in Reflex with no error, which the recovery does not clear (a known libfranka case), until
  `user-stop` (a person pressing and releasing the user stop) does;
- `--cutter`: the paper cutter in the hand, the fingertip board on `--pty` (below).

`ServerProcess` starts one and waits for READY; `close()` ends it; `kill()` ends it as a crash would.
"""
from __future__ import annotations

import argparse
import math
import os
import random
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

ROBOT_PORT, GRIPPER_PORT = 1337, 1338
STEP_S = 0.001
RESYNC_BEHIND_S = 1.0           # further behind than this, the schedule restarts from now (a stall);
                                # less, the steps catch up at once, so simulated time stays on the clock
JOINT7_KV = 40.0
SIM_RT_PRIORITY = 10            # SCHED_FIFO priority (below the kernel's threaded IRQs at 50)


def free_franka_host() -> str:
    """A 127.0.0.x address whose robot and hand ports are free."""
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        try:
            for port in (ROBOT_PORT, GRIPPER_PORT):
                with socket.create_server((host, port)):
                    pass
            return host
        except OSError:
            continue
    raise RuntimeError("no free 127.0.0.x address for franky-sim")


def _silent(host: str) -> None:
    """Accept on the robot's port and never answer."""
    srv = socket.create_server((host, ROBOT_PORT))
    print(f"READY {host}", flush=True)
    held = []
    while True:
        conn, _ = srv.accept()
        held.append(conn)


def _patch_connect_reply(version: int, status: str) -> None:
    """The robot server's Connect reply, as a robot of another system version gives it."""
    from franky_sim import franka_server as fs

    def handle(self, server, command_type_struct: str = "I"):
        header = fs.MessageHeader(self.command_type, self.command_id, 8)
        code = fs.ConnectStatus.kIncompatibleLibraryVersion if status == "incompatible" else fs.ConnectStatus.kSuccess
        self.client_socket.sendall(header.to_bytes(command_type_struct=command_type_struct)
                                   + struct.pack("<HH4x", code.value, version))
        if status != "incompatible":
            server._setup_udp_connection(self.network_udp_port)
    fs.ConnectCommand.handle = handle


# the cutter (`--cutter`): the hinge behind the grasp towards the robot, axis y, the handle a 25 mm
# bar from the hinge to the TCP; its base on the table slides against friction (a straight pull
# drags it); the fingertip is two compliant ball joints in series, the IMU's body between them, as
# in sim/mujoco_source.py, with the pad welded to the handle (the grasp)
ETA = 2.0                       # the fingertip's transmission (the stiffness ratio); the daemon's 30 N default
TIP_K_A = 2.0                   # N m/rad, finger -> IMU body
TIP_LAG_S = 0.003               # the silicone's damping on the IMU body: a first-order lag of the twist
TIP_ARMATURE = 5e-6             # kg m^2: MuJoCo's 1 ms step needs the springs' frequency under 1/dt
HINGE_FRICTION_NM = 0.05
BASE_FRICTION_N = 8.0           # the base's dry friction on the table, per axis
IMU_ODR_HZ = 6667
GYRO_NOISE_DENSITY = 8.7e-5     # rad/s/sqrt(Hz) (LSM6DSR: 5 mdps/sqrt(Hz))
ACCEL_NOISE_DENSITY = 5.9e-4    # m/s^2/sqrt(Hz) (60 ug/sqrt(Hz))
GYRO_BIAS_MAX = 0.02            # rad/s, the turn-on bias
GRASP_SOLREF = "0.02 1"         # the grasp weld's softness: a compliant grasp, as the daemon's arc admittance
                                # expects (with "0.005 1" the daemon's rotate tripped its divergence stop at
                                # every arc's end; with this it finished some, docs/franka.md)
IMU_CHUNK_STEPS = 5             # physics steps per write to the pseudo-terminal (5 ms)


def add_cutter(sim, radius: float, hinge_behind_m: float, hinge_friction_nm: float = HINGE_FRICTION_NM) -> dict:
    """The cutter and the fingertip in franky-sim's scene, before it starts. Returns the truth:
    the hinge point and axis (world), given the TCP at franky-sim's initial posture."""
    import xml.etree.ElementTree as ET

    import numpy as np

    from tecdard.robots.model import ArmModel
    q0 = (0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785)
    p_tcp = ArmModel("fr3").fk(np.array(q0)).translation
    hinge = p_tcp - np.array([hinge_behind_m, 0.0, 0.0])
    hand = next(b for b in sim.worldbody.iter("body") if b.get("name") == "robot0_hand")
    k_b = TIP_K_A / (ETA - 1.0)
    d_a = (TIP_K_A + k_b) * TIP_LAG_S
    joint = dict(type="ball", armature=str(TIP_ARMATURE), frictionloss="0", limited="false")
    imu = ET.SubElement(hand, "body", name="imu_body", pos="0 0 0.1034")
    ET.SubElement(imu, "joint", name="tip_a", stiffness=str(TIP_K_A), damping=str(d_a), **joint)
    ET.SubElement(imu, "geom", type="sphere", size="0.006", contype="0", conaffinity="0", mass="0.004")
    ET.SubElement(imu, "site", name="imu", pos="0 0 0")
    pad = ET.SubElement(imu, "body", name="pad", pos="0 0 0")
    ET.SubElement(pad, "joint", name="tip_b", stiffness=str(k_b), damping=str(1e-4 * k_b), **joint)
    ET.SubElement(pad, "geom", type="sphere", size="0.006", contype="0", conaffinity="0", mass="0.004")
    base = ET.SubElement(sim.worldbody, "body", name="cutter_base", pos=f"{hinge[0]} {hinge[1]} {hinge[2]}")
    for name, axis in (("base_x", "1 0 0"), ("base_y", "0 1 0")):
        ET.SubElement(base, "joint", name=name, type="slide", axis=axis, frictionloss=str(BASE_FRICTION_N),
                      damping="20")
    ET.SubElement(base, "geom", type="box", size="0.05 0.05 0.01", pos="0 0 -0.02", contype="0", conaffinity="0",
                  mass="2.0")
    handle = ET.SubElement(base, "body", name="handle", pos="0 0 0")
    ET.SubElement(handle, "joint", name="hinge", type="hinge", axis="0 1 0", range="-1.75 0", limited="true",
                  damping="0.02", frictionloss=str(hinge_friction_nm), armature="0")
    ET.SubElement(handle, "geom", type="capsule", fromto=f"0 0 0 {radius} 0 0", size="0.0125", contype="0",
                  conaffinity="0", mass="0.1")
    # nothing here touches anything (the grasp is a weld, the base slides on its joints): MuJoCo's
    # collision detection among the arm's meshes would only cost the simulator its real time
    option = sim.scene.find("option")
    if option is None:
        option = ET.SubElement(sim.scene, "option")
    ET.SubElement(option, "flag", contact="disable")
    eq = sim.scene.find("equality")
    # inactive until the arm stands at its initial posture (grasp()): MuJoCo would take the weld's
    # pose from qpos0, the arm stretched upright
    ET.SubElement(eq, "weld", name="grasp", body1="pad", body2="handle", anchor=f"{radius} 0 0", active="false",
                  solref=GRASP_SOLREF, torquescale="100")
    sensors = sim.scene.find("sensor")
    if sensors is None:
        sensors = ET.SubElement(sim.scene, "sensor")
    ET.SubElement(sensors, "gyro", site="imu", name="tip_gyro")
    ET.SubElement(sensors, "accelerometer", site="imu", name="tip_accel")
    ET.SubElement(sensors, "force", site="imu", name="grasp_force")
    return {"hinge_point": hinge.tolist(), "hinge_axis": [0.0, 1.0, 0.0], "radius": radius}


JOINT_REFLEX = 6                # libfranka's Errors: the joint_reflex flag's index
INJECTED = {"errors": False,    # a reflex the test asked for (--control), until the robot's error recovery
            "stuck": False}     # Reflex with no error (--control reflex-stuck), until `user-stop`


def report_state_extras(robot, sim, grasp_force: bool) -> None:
    """What franky-sim's robot state leaves out, as a real FR3 reports it:
    - with the cutter, the force the grasp transmits to the hand (O_F_ext_hat_K; franky-sim's is
      zeros and its joint torques carry its joints' friction): MuJoCo's force sensor between the
      hand and the fingertip, in the base frame, as the force on the robot;
    - a reflex the test injects (`--control`: the joint_reflex error flag, current and last),
      which franky-sim never raises; the robot's automatic error recovery clears it."""
    base = type(robot)

    class WithExtras(base):
        @property
        def state(self):
            st = base.state.fget(self)
            m, d = sim.model, sim.data
            extra = {}
            if grasp_force and m is not None:
                adr = m.sensor("grasp_force").adr[0]
                R = d.site_xmat[m.site("imu").id].reshape(3, 3)
                # MuJoCo's force sensor gives the force the hand exerts on the fingertip's subtree
                # (and the handle it holds); the robot's estimate is the force on the robot: its negative
                f = -(R @ d.sensordata[adr:adr + 3])
                extra["O_F_ext_hat_K"] = (*(float(x) for x in f), 0.0, 0.0, 0.0)
            if INJECTED["errors"]:
                # franky-sim packs `errors` as libfranka's current errors and `reflex_reason` as the
                # last motion's
                flags = tuple(i == JOINT_REFLEX for i in range(len(st.errors)))
                extra.update(errors=flags, reflex_reason=flags)
            return st.replace(**extra) if extra else st
    robot.__class__ = WithExtras


def _reflex_stuck_holds_the_mode() -> None:
    """`reflex-stuck`: the server reports Reflex with no error (it sets the mode itself, after the state's extras)."""
    from franky_sim import franka_robot_server as rs
    from franky_sim.franka_robot_protocol import RobotMode
    prop = rs.FrankaRobotServer.robot_state

    def robot_state(self):
        st = prop.fget(self)
        return st.replace(robot_mode=RobotMode.kReflex) if INJECTED["stuck"] else st
    rs.FrankaRobotServer.robot_state = property(robot_state)


def _recover_clears_the_injected_reflex() -> None:
    from franky_sim import franka_robot_protocol as rp
    handle = rp.AutomaticErrorRecoveryCommand.handle

    def recover(self, server):
        if INJECTED["errors"]:
            INJECTED["errors"] = False
            print("RECOVERED", flush=True)
        handle(self, server)
    rp.AutomaticErrorRecoveryCommand.handle = recover


HANDLE_WIDTH_M = 0.025         # the handle between the fingers (its capsule's diameter)


def _the_hand_holds_the_handle(sim) -> None:
    """The hand's commands act on the cutter as a real hand's would (franky-sim's fingers meet nothing: contacts
    are off): it starts holding the handle (the weld is on before READY); a grasp closes the fingers on the
    25 mm handle and welds the pad to it where they are; a move (an opening) lets go (the weld off)."""
    import mujoco
    from franky_sim import franka_gripper_server as gs
    cls = gs.FrankaGripperServer
    init, start_grasp, start_move = cls.__init__, cls.start_grasp, cls.start_move

    def weld(active: bool) -> None:
        if active:
            grasp(sim)
        else:
            sim.data.eq_active[sim.model.equality("grasp").id] = 0
            mujoco.mj_forward(sim.model, sim.data)

    def holding_init(self, robot, hostname):
        init(self, robot, hostname)
        self._is_grasping = True
        robot.set_hand_goal(HANDLE_WIDTH_M, 0.05, 70.0)

    def grasp_the_handle(self, width, speed, force, epsilon_inner, epsilon_outer, command_id, tcp_socket):
        start_grasp(self, width, speed, force, epsilon_inner, epsilon_outer, command_id, tcp_socket)
        self._robot.set_hand_goal(max(width, HANDLE_WIDTH_M), speed, force)     # the fingers stop on it
        weld(True)

    def open_the_hand(self, width, speed, command_id, tcp_socket):
        start_move(self, width, speed, command_id, tcp_socket)
        if width > HANDLE_WIDTH_M:
            weld(False)
    cls.__init__, cls.start_grasp, cls.start_move = holding_init, grasp_the_handle, open_the_hand


def _poll_control(path: str | None) -> None:
    """`--control PATH`: a test writes `reflex` there; the next poll injects it and removes the file."""
    if path and os.path.exists(path):
        with open(path) as f:
            what = f.read().strip()
        if not what:
            return      # the test's write_text has truncated the file but not written yet: the next poll reads it
        os.remove(path)
        if what == "reflex":
            INJECTED["errors"] = True
            print("REFLEX", flush=True)
        elif what == "reflex-stuck":
            INJECTED["stuck"] = True
            print("REFLEX-STUCK", flush=True)
        elif what == "user-stop":
            INJECTED["stuck"] = False
            print("USER-STOP", flush=True)


def grasp(sim) -> None:
    """Weld the pad to the handle where they are now. A weld's data are the anchor (body2's frame),
    that point in body1's frame, and body2's orientation relative to body1's (checked against
    MuJoCo's own compile-time values)."""
    import mujoco
    import numpy as np
    m, d = sim.model, sim.data
    mujoco.mj_forward(m, d)
    eq = m.equality("grasp").id
    b1, b2 = m.eq_obj1id[eq], m.eq_obj2id[eq]
    anchor = m.eq_data[eq, 0:3]
    R1, R2 = d.xmat[b1].reshape(3, 3), d.xmat[b2].reshape(3, 3)
    m.eq_data[eq, 3:6] = R1.T @ (d.xpos[b2] + R2 @ anchor - d.xpos[b1])
    q1_inv = np.zeros(4)
    mujoco.mju_negQuat(q1_inv, d.xquat[b1])
    rel = np.zeros(4)
    mujoco.mju_mulQuat(rel, q1_inv, d.xquat[b2])
    m.eq_data[eq, 6:10] = rel
    d.eq_active[eq] = 1


class FingertipBoard:
    """MuJoCo's gyro and accelerometer at the fingertip's IMU site, as the LSM6DSR on its board
    reports them: sampled at IMU_ODR_HZ from the 1 kHz physics (linear between steps), a turn-on
    gyro bias, white noise at the chip's densities, int16 at its full scales (sim.board.Board), in
    tecdar-imu/1 frames on a pseudo-terminal (sim.board.PtyDevice) that the daemon reads as its
    serial board."""

    def __init__(self, sim, link: str, seed: int = 1):
        import numpy as np

        from tecdard.sim.board import Board, BoardParams, PtyDevice
        self.np = np
        self.sim = sim
        self.device = PtyDevice(link)
        self.board = Board(BoardParams(odr_hz=IMU_ODR_HZ))
        self.rng = np.random.default_rng(seed)
        self.bias = self.rng.uniform(-GYRO_BIAS_MAX, GYRO_BIAS_MAX, 3)
        self.g_sigma = GYRO_NOISE_DENSITY * (IMU_ODR_HZ / 2.0) ** 0.5
        self.a_sigma = ACCEL_NOISE_DENSITY * (IMU_ODR_HZ / 2.0) ** 0.5
        self.t, self.rows = [], []
        self.next_sample = 0
        self._adr = None

    def post_step(self, sim) -> None:
        np = self.np
        model, data = sim.model, sim.data
        if self._adr is None:
            self._adr = (model.sensor("tip_gyro").adr[0], model.sensor("tip_accel").adr[0])
        g, a = self._adr
        self.t.append(float(data.time))
        self.rows.append(np.concatenate([data.sensordata[g:g + 3], data.sensordata[a:a + 3]]))
        if len(self.t) > IMU_CHUNK_STEPS:
            self._flush()

    def _flush(self) -> None:
        np = self.np
        t = np.array(self.t)
        rows = np.array(self.rows)
        k_end = int(np.floor(t[-1] * IMU_ODR_HZ))
        ks = np.arange(self.next_sample, k_end + 1)
        ks = ks[ks / IMU_ODR_HZ >= t[0]]
        if len(ks):
            ts = ks / IMU_ODR_HZ
            sig = np.column_stack([np.interp(ts, t, rows[:, j]) for j in range(6)])
            gyro = sig[:, :3] + self.bias + self.rng.normal(0.0, self.g_sigma, (len(ks), 3))
            accel = sig[:, 3:] + self.rng.normal(0.0, self.a_sigma, (len(ks), 3))
            try:
                self.device.write_frames(self.board.packets(gyro, accel))
            except OSError:
                pass                    # nobody reading, or unplugged: the board drops, as a real one
            self.next_sample = int(ks[-1]) + 1
        self.t, self.rows = self.t[-1:], self.rows[-1:]


def run(args) -> None:
    if args.silent:
        _silent(args.host)
        return
    if args.reply_version is not None or args.reply_status != "ok":
        _patch_connect_reply(10 if args.reply_version is None else args.reply_version, args.reply_status)
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MUJOCO_DEFAULT_KV, MujocoSimulator
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    kv = tuple(MUJOCO_DEFAULT_KV[:6]) + (args.joint7_kv,)
    _recover_clears_the_injected_reflex()
    _reflex_stuck_holds_the_mode()
    with MujocoSimulator() as sim:
        robot = sim.add_robot(kv=kv)
        report_state_extras(robot, sim, grasp_force=args.cutter)
        board = None
        if args.cutter:
            truth = add_cutter(sim, args.radius, args.radius, args.hinge_friction)
            _the_hand_holds_the_handle(sim)
            board = FingertipBoard(sim, args.pty)
            sim.register_post_step_callback(board.post_step)
            truth_path = args.truth
        with SimulationServer(sim, hostname_candidates=[args.host]) as server:
            truth_out = None
            if board is not None:
                grasp(sim)                  # before READY: a test never meets the hand not yet holding
                truth_out = TruthWriter(truth_path)
                truth_out.put(_truth_now(truth, sim))
            realtime = _keep_real_time()
            print(f"READY {args.host} {realtime}", flush=True)
            next_t = started = time.monotonic()
            behind = 0
            worst_behind = window_behind = 0.0
            late: list = []             # [simulated time, worst behind in that truth window] above LATE_LOG_MIN_S
            steps = 0
            while not stop.is_set():
                server.run_once(realtime=False)
                steps += 1
                if steps % TRUTH_EVERY_STEPS == 0:
                    _poll_control(args.control)
                    if window_behind > LATE_LOG_MIN_S:
                        late = (late + [[float(sim.data.time), window_behind]])[-LATE_LOG_LEN:]
                    window_behind = 0.0
                    if truth_out is not None:
                        truth.update(resyncs=behind, worst_behind_s=worst_behind, late=late,
                                     wall_s=time.monotonic() - started)
                        truth_out.put(_truth_now(truth, sim))
                next_t += STEP_S
                delay = next_t - time.monotonic()
                worst_behind = max(worst_behind, -delay)
                window_behind = max(window_behind, -delay)
                if delay > 0:
                    time.sleep(delay)
                elif delay < -RESYNC_BEHIND_S:
                    behind += 1
                    next_t = time.monotonic()
            if truth_out is not None:
                truth_out.close()


TRUTH_EVERY_STEPS = 50          # the truth file is rewritten every 50 ms of simulated time
LATE_LOG_MIN_S = 0.010          # truth["late"]: each 50 ms window that fell further behind than this,
LATE_LOG_LEN = 400              # the last this many, so a test can judge the lateness during its task alone


def _truth_now(truth: dict, sim) -> dict:
    """The scene's truth for the test: `truth` (the hinge, and how the schedule has kept),
    simulated time, the handle's angle, the base's displacement."""
    data = sim.data
    base = sim.model.joint("base_x").qposadr[0], sim.model.joint("base_y").qposadr[0]
    hinge = sim.model.joint("hinge").qposadr[0]
    return dict(truth, sim_time_s=float(data.time), handle_angle_deg=-math.degrees(float(data.qpos[hinge])),
                base_displacement=float((data.qpos[base[0]] ** 2 + data.qpos[base[1]] ** 2) ** 0.5))


class TruthWriter:
    """Writes the latest truth as JSON (whole, then renamed) on a thread of its own: a file write
    on a busy disk blocked the 1 kHz loop for 20-90 ms, a stall of the robot and the board that
    the daemon rightly reads as stale data."""

    def __init__(self, path: str):
        self.path = path
        self._latest: dict | None = None
        self._wake = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="truth", daemon=True)
        self._thread.start()

    def put(self, truth: dict) -> None:
        with self._wake:
            self._latest = truth
            self._wake.notify()

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(5)

    def _run(self) -> None:
        import json
        while True:
            with self._wake:
                while self._latest is None and not self._closed:
                    self._wake.wait()
                out, self._latest = self._latest, None
                if out is None:
                    return
            tmp = self.path + ".tmp"
            with open(tmp, "w") as f:
                json.dump(out, f)
            os.replace(tmp, self.path)


def _keep_real_time() -> str:
    """A real robot never falls behind; a simulator sharing 2 cores with the daemon and franky
    did, by 50-550 ms at a time, and the daemon then saw a robot whose world ran late. Where the
    host allows it (root, or CAP_SYS_NICE) the simulation's thread runs at a real-time priority:
    it needs about 65 % of a core and sleeps the rest of each step, so it never starves the
    others (the truth's writer thread, started before, keeps the normal policy). Returns which it
    got."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(SIM_RT_PRIORITY))
        return "SCHED_FIFO"
    except OSError:                 # EPERM without the privilege
        pass
    try:
        os.nice(-10)
        return "nice-10"
    except OSError:
        return "normal"


class ServerProcess:
    """franky-sim in a child process on a free loopback address."""

    def __init__(self, *extra: str, host: str | None = None, ready_s: float = 60.0):
        self.host = host or free_franka_host()
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.fakes.franka_sim", "--host", self.host, *extra],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
        self.output: list[str] = []
        ready = threading.Event()

        def drain():
            for line in self.proc.stdout:
                self.output.append(line.rstrip())
                if line.startswith(f"READY {self.host}"):
                    ready.set()
        threading.Thread(target=drain, daemon=True).start()
        if not ready.wait(ready_s):
            self.kill()
            raise RuntimeError(f"franky-sim did not start on {self.host}: {self.output[-5:]}")

    def kill(self) -> None:
        """End it as a crash would: no goodbye on any socket."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", required=True)
    ap.add_argument("--reply-version", type=int, default=None)
    ap.add_argument("--reply-status", choices=("ok", "incompatible"), default="ok")
    ap.add_argument("--silent", action="store_true")
    ap.add_argument("--joint7-kv", type=float, default=JOINT7_KV)
    ap.add_argument("--cutter", action="store_true", help="the paper cutter in the hand, the fingertip IMU on --pty")
    ap.add_argument("--radius", type=float, default=0.15, help="the handle's length, hinge to TCP, m")
    ap.add_argument("--hinge-friction", type=float, default=HINGE_FRICTION_NM, help="the hinge's dry friction, N m")
    ap.add_argument("--pty", default=None, help="the fingertip board's device link (with --cutter)")
    ap.add_argument("--truth", default=None, help="the scene's truth, JSON (with --cutter)")
    ap.add_argument("--control", default=None, help="a file the test writes `reflex` to, to inject one")
    run(ap.parse_args())


if __name__ == "__main__":
    main()
