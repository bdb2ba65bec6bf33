"""What the ROS 2 node costs, how fast a contact reaches ROS 2, and the observer backend's hinge error
(issue 36); writes benchmarks/ros2.md.

    python -m benchmarks.ros2 [--seconds S]

- Encoding: each message the node publishes, built and encoded to CDR (rosbags) on one thread, in
  microseconds (the median of many).
- The daemon on the simulated robot, idle for S seconds and then through one `rotate` of 20 degrees,
  without the node and with it (a Zenoh router between it and zenoh-ros2-sdk subscribed to `imu`
  at 1 kHz and `tcp_pose`): its own process's CPU (the simulator's child excluded), and the control
  tick's work and lateness p99 and overruns from its `status`.
- Contact latency: zenoh-ros2-sdk subscribed to `contact` during the rotate, through the router on
  loopback: its arrival (system clock) minus the message's stamp, the time of the estimate's last IMU
  sample.
- The observer backend (`robot.backend: ros2`): tests/fakes/ros2_arm.py moves the simulator's Panda along a
  20 degree arc about the cutter's hinge and publishes its joint states at 200 Hz; the daemon's last
  contact before the arc's end, its distance to the true hinge axis, over RUNS runs.
The machine is shared: the figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.ur import cpu_s  # noqa: E402
from tecdard.ros2 import messages as M  # noqa: E402
from tecdard.runtime.ros2_node import TOPICS  # noqa: E402
from tecdard.ros2.typesupport import TypeSupport  # noqa: E402
from tests.conftest import DaemonProcess, daemon_config  # noqa: E402
from tecdard.tools.demo import distance_to_axis  # noqa: E402
from tests.test_ros2_node import (ARC_DEG, ARC_RADIUS_M, ARC_SPEED_M_S, RosArm, Subscription,  # noqa: E402
                                  observer_config, stamp_s, start_router)

ENCODE_N = 2000
RUNS = 3
SETTLE_S = 3.0


class Est:
    p, std, cov, axis, converged, t = (np.array([0.3, 0.0, 0.45]), np.full(3, 1e-3), np.eye(3) * 1e-6,
                                       np.array([0.0, 1.0, 0.0]), True, 1.0)


def encode_costs() -> dict[str, float]:
    """µs per message, built and encoded."""
    ts = TypeSupport()
    state_text = json.dumps({"t": 1.0, "kind": "contact_onset", "task": "rotate-1"})
    makers = {
        "contact": lambda: M.contact(ts, Est, 1.7e9, "base_link"),
        "contact_marker (both)": lambda: M.contact_markers(ts, Est, 1.7e9, "base_link"),
        "imu": lambda: M.imu(ts, 1.7e9, [0.1, 0.2, 0.3], [0.0, 0.0, 9.81], "fingertip_imu"),
        "tcp_pose": lambda: M.tcp_pose(ts, [0.3, 0.0, 0.5], [0, 0, 0, 1], 1.7e9, "base_link"),
        "events": lambda: M.event(ts, {"kind": "contact_onset", "task": "rotate-1"}, 1.7e9, state_text),
        "/tf": lambda: M.contact_tf(ts, Est, 1.7e9, "base_link", "sim/contact"),
        "/diagnostics": lambda: M.diagnostics(ts, 1.7e9, [(f"tecdard/sim: {k}", 0, "ok", {"a": 1, "b": 2})
                                                          for k in range(5)]),
    }
    types = {name.split(" ")[0]: TOPICS[name.split(" ")[0]][0] for name in makers}
    out = {}
    for name, make in makers.items():
        typ = types[name.split(" ")[0]]
        samples = []
        for _ in range(ENCODE_N):
            t0 = time.perf_counter()
            msg = make()
            for m in (msg if isinstance(msg, list) else [msg]):
                ts.encode(m, typ)
            samples.append(time.perf_counter() - t0)
        out[name] = float(np.median(samples)) * 1e6
    return out


def run(seconds: float, with_ros2: bool, subscribed: bool = True) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        port, router = start_router()
        subs = []
        try:
            overrides = {"zenoh.connect": [f"tcp/127.0.0.1:{port}"]}
            if with_ros2:
                overrides["ros2"] = {"enabled": True}
            d = DaemonProcess(pathlib.Path(tmp), daemon_config(**overrides))
            try:
                if with_ros2 and subscribed:
                    for topic, typ in (("/sim/imu", "sensor_msgs/msg/Imu"),
                                       ("/sim/tcp_pose", "geometry_msgs/msg/PoseStamped")):
                        subs.append(subprocess.Popen(
                            [sys.executable, "-m", "tests.fakes.ros2_client", str(port), "subscribe",
                             json.dumps({"topic": topic, "type": typ, "count": 10**9, "timeout": 3 * seconds + 120})],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True))
                    for s in subs:
                        s.stdout.readline()
                time.sleep(SETTLE_S)
                c0, t0 = cpu_s(d.proc.pid), time.monotonic()
                time.sleep(seconds)
                idle = (cpu_s(d.proc.pid) - c0) / (time.monotonic() - t0)
                ctl_idle = d.client.command("status")["state"]["control"]
                watch = Subscription(port, [["/sim/contact", "geometry_msgs/msg/PoseWithCovarianceStamped", 10**6]],
                                     25.0) if with_ros2 and subscribed else None
                reply = d.client.command("rotate", {"angle_deg": 20})
                c0, t0 = cpu_s(d.proc.pid), time.monotonic()
                ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 120.0)
                busy = (cpu_s(d.proc.pid) - c0) / (time.monotonic() - t0)
                ctl = d.client.command("status")["state"]["control"]
                latency = [] if watch is None else [m["_rx"] - stamp_s(m) for m in watch.result()["/sim/contact"]]
                return {"idle_cpu": idle, "rotate_cpu": busy, "idle": ctl_idle, "rotate": ctl, "result": ev["kind"],
                        "latency_s": latency}
            finally:
                d.close()
        finally:
            for s in subs:
                s.kill()
            router.kill()


def observer_errors(runs: int) -> list[float]:
    """The observer backend's hinge error at the end of the harness's arc, m, per run."""
    out = []
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            port, router = start_router()
            arm = RosArm(pathlib.Path(tmp), port)
            d = None
            try:
                (pathlib.Path(tmp) / "d").mkdir()
                d = DaemonProcess(pathlib.Path(tmp) / "d", observer_config(arm.info["pty"], port))
                arc_s = np.radians(ARC_DEG) * ARC_RADIUS_M / ARC_SPEED_M_S
                watch = Subscription(port, [["/sim/contact", "geometry_msgs/msg/PoseWithCovarianceStamped", 10**6]],
                                     arc_s + 3.0)
                truth = arm.say(f"arc {ARC_DEG} {ARC_SPEED_M_S}")["truth"]
                t_done = time.time()
                last = [m for m in watch.result()["/sim/contact"] if stamp_s(m) <= t_done][-1]
                p = np.array([last["pose"]["pose"]["position"][k] for k in "xyz"])
                out.append(distance_to_axis(p, np.array(truth["hinge_point"]), np.array(truth["hinge_axis"])))
            finally:
                if d is not None:
                    d.close()
                arm.close()
                router.kill()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    costs = encode_costs()
    off = run(args.seconds, False)
    alone = run(args.seconds, True, subscribed=False)
    on = run(args.seconds, True)
    lines = [
        f"# The ROS 2 node: its cost ({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()})", "",
        "`python -m benchmarks.ros2`. The machine is shared; nothing here is a test.", "",
        "## Building and encoding one message (rosbags, on the main thread's publish pass)", "",
        "| topic | µs per message (median) |", "|---|---|",
        *[f"| `{name}` | {us:.1f} |" for name, us in costs.items()], "",
        f"At `imu_rate_hz` 1000 and 50 `tcp_pose` a second, the node encodes about "
        f"{(1000 * costs['imu'] + 50 * costs['tcp_pose']) / 1e4:.1f} % of one core's time.", "",
        f"## The daemon on the simulated robot, idle for {args.seconds:g} s, then one `rotate` of 20 deg", "",
        "Without the node; with it and nobody subscribed (a topic nobody takes is not built); and with "
        "zenoh-ros2-sdk subscribed to `imu` (1 kHz) and `tcp_pose` through the router, in two processes of "
        "their own on the same two cores. CPU: the daemon's own process, the simulator's child excluded. Ticks: the control "
        "thread's statistics over its last 1000 ticks, read from `status` at the end of each phase.", "",
        "| | CPU idle | CPU rotating | tick work p99 idle / rotating, ms | tick lateness p99 idle / rotating, ms "
        "| overruns | rotate |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in (("without the node", off), ("with the node, nobody subscribed", alone),
                    ("with the node, `imu` and `tcp_pose` subscribed", on)):
        lines.append(f"| {name} | {100 * r['idle_cpu']:.1f} % | {100 * r['rotate_cpu']:.1f} % | "
                     f"{r['idle'].get('work_ms_p99', float('nan')):.2f} / {r['rotate'].get('work_ms_p99', float('nan')):.2f} | "
                     f"{r['idle'].get('late_ms_p99', float('nan')):.2f} / {r['rotate'].get('late_ms_p99', float('nan')):.2f} | "
                     f"{r['rotate'].get('overruns')} | {r['result']} |")
    lat = np.array(on["latency_s"]) * 1e3
    errs = np.array(observer_errors(RUNS)) * 1e3
    lines += ["", "## A contact's latency to ROS 2", "",
              f"During the rotate, zenoh-ros2-sdk took {len(lat)} `contact` messages through the router on loopback: "
              "arrival minus stamp (the estimate's last IMU sample), which includes the estimator's batching "
              "(one output period), the hand-over to the main thread's publish pass, the encoding and Zenoh.", "",
              "| p50 | p90 | p99 | max |", "|---|---|---|---|",
              (f"| {np.percentile(lat, 50):.1f} ms | {np.percentile(lat, 90):.1f} ms | {np.percentile(lat, 99):.1f} ms "
               f"| {lat.max():.1f} ms |") if len(lat) else "| - | - | - | - |", "",
              f"## The observer backend's hinge error ({RUNS} runs)", "",
              "tests/fakes/ros2_arm.py moves the simulator's Panda along a 20 deg arc about the cutter's hinge at 10 mm/s "
              "and publishes its joint states at 200 Hz through zenoh-ros2-sdk; the daemon on `robot.backend: ros2` "
              "reads them and its board on a pty. The last contact published before the arc's end, from the true "
              "hinge axis:", "",
              "| run | " + " | ".join(str(k + 1) for k in range(len(errs))) + " |",
              "|---|" + "---|" * len(errs),
              "| error, mm | " + " | ".join(f"{e:.2f}" for e in errs) + " |", ""]
    text = "\n".join(lines)
    (ROOT / "benchmarks" / "ros2.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
