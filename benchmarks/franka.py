"""The Franka backend's link against franky-sim (issue 22); writes benchmarks/franka.md.

    python -m benchmarks.franka

franky-sim (tests/fakes/franka_sim.py: one FR3 and its hand over MuJoCo, on an absolute 1 kHz schedule)
in a child process, the real franky client in the link's child (robots/franka_link.py), as the
daemon runs them. Measured:
- the state rate: every robot state, and the daemon's default share (robot.franka.state_rate_hz);
- command to motion: from `command_joint_velocity` to the first state whose joint 1 rate reads
  1 mrad/s, from rest, over repeated commands;
- CPU, as a share of one core: the simulator's process, the link's child (franky, libfranka's
  1 kHz loop, the force from the joint torques) and the daemon side (the link's reader thread),
  while the arm is commanded at 50 Hz as the control tick does (500 states per second to the daemon);
- the daemon's `rotate` 30 deg on franky-sim's paper cutter, next to the simulated backend's.
"""
from __future__ import annotations

import os
import pathlib
import platform
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.robots.franka_link import FrankaLink, FrankaLinkSettings  # noqa: E402
from tests.fakes.franka_sim import ServerProcess  # noqa: E402

RATE_S = 5.0
LATENCY_RUNS = 20
MOVING_RAD_S = 1e-3
CPU_S = 10.0
TICK_S = 0.02


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process, s (/proc)."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


ROTATE_RUNS = 8
HINGE_FRICTION_NM = 0.3


def rotate_runs(n: int = ROTATE_RUNS) -> list[dict]:
    """The daemon's `rotate` 30 deg on franky-sim's cutter (tests/fakes/franka_sim.py --cutter), as a
    rig would run it: the daemon on robot.backend franka, the fingertip board on the scene's pty.
    Each run's outcome, hinge error (m), handle angle (deg) and base displacement (m) from the
    scene's truth, and how far franky-sim fell behind its schedule (s)."""
    import tempfile

    from tecdard.tools.demo import distance_to_axis
    from tests.test_daemon_franka import cutter_run
    out = []
    for _ in range(n):
        with tempfile.TemporaryDirectory() as tmp:
            ev, truth, _, _ = cutter_run(pathlib.Path(tmp), "--hinge-friction", str(HINGE_FRICTION_NM))
        run = {"ok": ev["kind"] == "task_done", "error": ev.get("error"), "angle_deg": truth["handle_angle_deg"],
               "base_m": truth["base_displacement"], "behind_s": truth.get("worst_behind_s", float("nan"))}
        if run["ok"]:
            run["hinge_m"] = distance_to_axis(np.array(ev["result"]["hinge"]["p"]), np.array(truth["hinge_point"]),
                                              np.array(truth["hinge_axis"]))
        out.append(run)
    return out


def main() -> None:
    srv = ServerProcess()
    rates = {}
    for hz in (1000.0, 500.0):          # every state the robot sends, then the daemon's default share
        link = FrankaLink(FrankaLinkSettings(srv.host, realtime="ignore", connect_timeout_s=10.0, state_rate_hz=hz))
        link.start()
        first = link.wait_state(-1, 2.0)
        time.sleep(RATE_S)
        rates[hz] = (link.read_state().seq - first.seq) / RATE_S
        link.stop()
        time.sleep(0.5)
    link = FrankaLink(FrankaLinkSettings(srv.host, realtime="ignore", connect_timeout_s=10.0))
    t0 = time.monotonic()
    link.start()
    connect_s = time.monotonic() - t0
    try:
        link.wait_state(-1, 2.0)

        latencies = []
        qd = np.zeros(7)
        for k in range(LATENCY_RUNS):
            qd[0] = 0.1 if k % 2 == 0 else -0.1                 # back and forth: the arm stays near home
            js = link.read_state()
            t_cmd = time.monotonic()
            link.command_joint_velocity(qd)
            seq = js.seq
            while time.monotonic() - t_cmd < 1.0:
                js = link.wait_state(seq, 0.1)
                seq = js.seq
                if abs(js.qd[0]) > MOVING_RAD_S:
                    latencies.append(time.monotonic() - t_cmd)
                    break
            for _ in range(10):
                link.command_joint_velocity(qd)
                time.sleep(TICK_S)
            link.hold()
            time.sleep(0.4)

        c_srv, c_child = cpu_seconds(srv.proc.pid), cpu_seconds(link._proc.pid)
        c_self, w0 = time.process_time(), time.monotonic()
        k = 0
        while time.monotonic() - w0 < CPU_S:
            qd[0] = 0.1 * np.sin(2 * np.pi * 0.25 * (time.monotonic() - w0))
            link.command_joint_velocity(qd)
            k += 1
            time.sleep(max(0.0, w0 + k * TICK_S - time.monotonic()))
        wall = time.monotonic() - w0
        cpu = {"simulator (franky-sim, MuJoCo at 1 kHz)": (cpu_seconds(srv.proc.pid) - c_srv) / wall,
               "the link's child (franky, libfranka's loop, force from torques)": (cpu_seconds(link._proc.pid) - c_child) / wall,
               "daemon side (the link's reader thread, 50 Hz commands)": (time.process_time() - c_self) / wall}
        link.hold()
    finally:
        link.stop()
        srv.close()
    lat = np.array(latencies) * 1e3
    lines = [f"# Franka backend against franky-sim ({time.strftime('%Y-%m-%d')}, {platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()})", "",
             "\n".join(__doc__.split("\n\n")[1:3]).replace("\n", " "), "",
             "| figure | value |", "|---|---|",
             f"| connect (version probe, franky.Robot, franky.Gripper, first state) | {connect_s:.2f} s |",
             f"| robot states received, all (state_rate_hz 1000) | {rates[1000.0]:.0f} per second |",
             f"| robot states the daemon takes (state_rate_hz 500, the default) | {rates[500.0]:.0f} per second |",
             f"| command to motion, median (min-max) over {len(lat)} | {np.median(lat):.1f} ms "
             f"({lat.min():.1f}-{lat.max():.1f}) |"]
    lines += [f"| CPU, {name} | {100 * share:.1f} % of a core |" for name, share in cpu.items()]
    runs = rotate_runs()
    done = [r for r in runs if r["ok"]]
    lines += ["", f"## `rotate` 30 deg on franky-sim's cutter ({len(runs)} runs, hinge friction {HINGE_FRICTION_NM} N m)", "",
              "| run | outcome | hinge error | handle angle | base moved | franky-sim behind its schedule, worst |",
              "|---|---|---|---|---|---|"]
    for k, r in enumerate(runs, 1):
        lines.append(f"| {k} | {'done' if r['ok'] else r['error']} | "
                     + (f"{r['hinge_m'] * 1e3:.2f} mm" if r["ok"] else "-")
                     + f" | {r['angle_deg']:.1f} deg | {r['base_m'] * 1e3:.2f} mm | {r['behind_s'] * 1e3:.0f} ms |")
    lines += ["", f"{len(done)} of {len(runs)} finished"
              + (f"; hinge error median {np.median([r['hinge_m'] for r in done]) * 1e3:.2f} mm" if done else "")
              + ". On the simulated backend every hinge pose finishes (its figures: benchmarks/poses.md, benchmarks/daemon.md). "
              "franky-sim shares the 2 cores with the daemon and franky; it runs at a real-time priority where "
              "the host allows, and the last column is how far it fell behind its 1 kHz schedule (docs/franka.md)."]
    lines += ["", "Command to motion covers the pipe to the child, franky's motion start (a new JointVelocityMotion "
              "preempting the last), libfranka's next 1 kHz command packet, the simulator's step and the state "
              "that reports the joint moving. From rest the motion ramps up at franky's jerk limit "
              "(relative_dynamics_factor 0.5), so the first mrad/s comes a few steps after the command lands.", ""]
    text = "\n".join(lines) + "\n"
    (ROOT / "benchmarks" / "franka.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
