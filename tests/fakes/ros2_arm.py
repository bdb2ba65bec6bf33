"""An arm that ROS 2 drives, for the observer backend's tests: the simulator's Panda holding the paper
cutter, moved by this harness (as ros2_control would move it) and published as sensor_msgs/JointState by
zenoh-ros2-sdk, with its fingertip board streaming on a pty.

    python -m tests.fakes.ros2_arm ROUTER_PORT CONFIG_YAML   [then lines on stdin]

Prints {"pty": path, "joints": [...]} once the arm streams. Then, line by line on stdin:
- `arc DEG SPEED`: the TCP follows an arc of DEG degrees about the cutter's true hinge at SPEED m/s (the
  gripper turning with the handle), servoed at 50 Hz; prints {"done": true, "truth": {...}} at the end;
- `fault stop|jump|names`: from now on the stream stops, jumps 0.5 rad on joint 1 for JUMP_S, or names the
  joints wrongly;
- `quit`.
JointStates go out at RATE_HZ, each stamped with its sample's time on the system clock, and beside each the
simulator's contact force at the TCP as geometry_msgs/WrenchStamped on /wrench in `base_link` (as a driver's
force-torque broadcaster would publish it, transformed to the base).
"""
from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import threading
import time

import numpy as np

RATE_HZ = 200.0
JUMP_S = 0.05                  # `fault jump`: how long the joint stays 0.5 rad off
TICK_S = 0.02


def main() -> None:
    port, config = int(sys.argv[1]), sys.argv[2]
    os.environ["ZENOH_CONFIG_OVERRIDE"] = ('scouting/multicast/enabled=false;listen/endpoints=["tcp/127.0.0.1:0"];'
                                           'connect/retry={"period_init_ms":100,"period_max_ms":200}')
    os.environ["ZENOH_ROS2_SDK_CACHE"] = tempfile.mkdtemp(prefix="ros2-sdk-cache-")
    import pinocchio as pin
    import zenoh_ros2_sdk as sdk
    from tecdard.config import Config
    from tecdard.robots import backends
    from tecdard.robots.model import ArmModel
    from tests.fakes.ros2_client import definitions_dir, joint_state

    sdk.get_registry(definitions_dir())
    cfg = Config.load(config)
    robot = cfg.section("robot")
    model = ArmModel(robot.getstr("model"))
    q_home = np.array(robot.getfloats("q_home", n=model.nq))
    sim = backends.build("sim", backends.BackendContext(cfg, model, q_home, [0.0, 0.0, 0.0, 1.0], TICK_S))
    sim.imu_source("sim-wire", cfg.section("imu"))       # the board on a pty (sim.spec.pty_link)
    sim.start()
    pub = sdk.ROS2Publisher("/joint_states", "sensor_msgs/msg/JointState", router_port=port,
                            node_name="tecdar_test_arm")
    wrench_pub = sdk.ROS2Publisher("/wrench", "geometry_msgs/msg/WrenchStamped", router_port=port,
                                   node_name="tecdar_test_arm")
    types = pub.session_mgr.store.types
    wtypes = wrench_pub.session_mgr.store.types
    names = list(model.joint_names)
    fault = {"kind": None}
    stop = threading.Event()

    def publish() -> None:
        seq, t_next, jumped = -1, time.monotonic(), False
        while not stop.is_set():
            t_next += 1.0 / RATE_HZ
            js = sim.read_state()
            if js.seq != seq and fault["kind"] != "stop":
                seq = js.seq
                q = np.array(js.q, float)
                if fault["kind"] == "jump" and (jumped is False or time.monotonic() < jumped):
                    q[0] += 0.5          # for JUMP_S: a glitch shorter than a control tick is never read
                    jumped = jumped or time.monotonic() + JUMP_S
                stamp = time.time() - (time.monotonic() - js.t)
                ns = int(stamp * 1e9)
                msg = {"header": {"stamp": [ns // 10**9, ns % 10**9], "frame_id": ""},
                       "name": [n + "_x" for n in names] if fault["kind"] == "names" else names,
                       "position": q.tolist(), "velocity": list(map(float, js.qd))}
                pub.publish(**joint_state(types, msg))
                f = np.zeros(3) if js.tcp_force is None else np.asarray(js.tcp_force, float)
                V = wtypes["geometry_msgs/msg/Vector3"]
                wrench_pub.publish(
                    header=wtypes["std_msgs/msg/Header"](stamp=wtypes["builtin_interfaces/msg/Time"](
                        sec=ns // 10**9, nanosec=ns % 10**9), frame_id="base_link"),
                    wrench=wtypes["geometry_msgs/msg/Wrench"](force=V(x=float(f[0]), y=float(f[1]), z=float(f[2])),
                                                              torque=V(x=0.0, y=0.0, z=0.0)))
            time.sleep(max(0.0, t_next - time.monotonic()))
    threading.Thread(target=publish, daemon=True).start()
    time.sleep(0.5)
    print(json.dumps({"pty": sim.spec.pty_link, "joints": names}), flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "arc":
            arc(sim, model, q_home, math.radians(float(words[1])), float(words[2]), pin)
            truth = sim.truth()
            print(json.dumps({"done": True, "truth": {"hinge_point": truth.hinge_point.tolist(),
                                                      "hinge_axis": truth.hinge_axis.tolist(),
                                                      "angle_deg": math.degrees(truth.handle_angle_rad)}}), flush=True)
        elif words[0] == "fault":
            fault["kind"] = words[1]
            print(json.dumps({"fault": words[1]}), flush=True)
        elif words[0] == "quit":
            break
    stop.set()
    sim.close()
    os._exit(0)


def arc(sim, model, q_home, angle_rad: float, speed_m_s: float, pin) -> None:
    """The TCP along an arc about the true hinge (its point and axis from the simulator's truth), the tool
    turning with it, at speed_m_s along the arc: as a controller that knows the geometry would move it."""
    truth = sim.truth()
    h, axis = np.asarray(truth.hinge_point, float), np.asarray(truth.hinge_axis, float)
    js = sim.read_state()
    o0 = model.fk(np.asarray(js.q, float))
    p0, R0 = o0.translation.copy(), o0.rotation.copy()
    radius = np.linalg.norm(np.cross(axis, p0 - h))
    # the handle lifts: turn the way whose tangent at the start points up (+z)
    sign = 1.0 if np.cross(axis, p0 - h)[2] >= 0 else -1.0
    w = sign * speed_m_s / radius
    duration = abs(angle_rad / w)
    t0 = time.monotonic()
    t_next = t0
    while True:
        t_next += TICK_S
        s = min(time.monotonic() - t0, duration)
        Rt = pin.exp3(axis * w * s)
        p_des, R_des = h + Rt @ (p0 - h), Rt @ R0
        omega = axis * w if s < duration else np.zeros(3)
        js = sim.read_state()
        q = np.asarray(js.q, float)
        oM = model.fk(q)
        twist = model.servo_twist(oM, p_des, np.cross(omega, p_des - h), R_des, omega)
        sim.command_joint_velocity(model.dls_velocity(q, twist, q_home))
        if s >= duration:
            break
        time.sleep(max(0.0, t_next - time.monotonic()))
    sim.hold()
    time.sleep(0.3)


if __name__ == "__main__":
    main()
