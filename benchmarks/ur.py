"""The UR backend against the fake UR controller (issue 19); writes benchmarks/ur.md.

    python -m benchmarks.ur [--seconds S] [--rotates N]

Everything runs through the real ur-rtde client (in robots.ur_link's child process) against
tests/fakes/fake_ur.py on a free 127.0.0.x address:
- state rate: new controller states the link hands out per second (an e-Series controller: 500 Hz);
- command latency: from `command_joint_velocity` in the daemon's process to the fake's control
  script seeing the new speedJ target in its registers (each command a distinct target), and to the
  arm's first motion after a command from rest;
- CPU: the link's child process (the ur-rtde clients) and the daemon-side process (the link's
  reader thread and a 50 Hz command loop), as shares of one core, from /proc;
- rotate: the whole daemon's 30 deg `rotate` through the fake whose arm is our simulator (the
  paper cutter, the fingertip board on a pty), as tests/test_ur_rotate.py runs it.
The machine is shared: figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import platform
import statistics
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.robots.ur_link import UrLink, UrLinkSettings  # noqa: E402
from tests.fakes.fake_ur import FakeController, free_loopback_host, wait_for  # noqa: E402

TICK_S = 0.02
SLOW_ACCEL_RAD_S2 = 1.0        # ur-rtde's usual speedJ acceleration, for comparison with our default
CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User plus system CPU time of a process, s."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def stream(seconds: float) -> dict:
    """State rate, command latency and CPU over `seconds` of commands at the control tick."""
    fake = FakeController(free_loopback_host(), arm="UR5e", q=(0.1, -1.2, 1.3, -1.6, -1.57, 0.2))
    link = UrLink(UrLinkSettings(fake.host, connect_timeout_s=5.0))
    try:
        link.start()
        js = link.wait_state(-1, 2.0)
        child = link._proc.pid
        # from rest: the first command's way to the arm's first motion
        t_first = time.monotonic()
        link.command_joint_velocity(np.array([0.05, 0, 0, 0, 0, 0]))
        wait_for(lambda: fake.arm()["moved_t"] is not None, 2.0)
        first_motion_ms = (fake.arm()["moved_t"] - t_first) * 1e3
        sent = {}
        seq0, t0 = js.seq, time.monotonic()
        cpu_child0, cpu_self0 = cpu_s(child), time.process_time()
        k = 0
        t_next = time.monotonic()
        while time.monotonic() - t0 < seconds:
            k += 1
            target = (0.05 + 1e-5 * (k % 1000), 0.0, 0.0, 0.0, 0.0, 0.0)
            sent[round(target[0], 9)] = time.monotonic()
            link.command_joint_velocity(np.array(target))
            t_next += TICK_S
            time.sleep(max(0.0, t_next - time.monotonic()))
        elapsed = time.monotonic() - t0
        states = link.read_state().seq - seq0
        cpu_child, cpu_self = cpu_s(child) - cpu_child0, time.process_time() - cpu_self0
        link.hold()
        seen = fake.arm()["speedj_t"]
        latencies = [(t - sent[round(v[0], 9)]) * 1e3 for t, v in seen if round(v[0], 9) in sent]
        latencies = [x for x in latencies if x >= 0]
        return {"state_hz": states / elapsed, "commands": k, "seen": len(latencies),
                "lat_median_ms": statistics.median(latencies), "lat_p99_ms": float(np.percentile(latencies, 99)),
                "lat_max_ms": max(latencies), "first_motion_ms": first_motion_ms,
                "cpu_child": cpu_child / elapsed, "cpu_self": cpu_self / elapsed, "seconds": elapsed}
    finally:
        link.stop()
        fake.close()


def rotates(n: int, accel_rad_s2: float | None = None) -> list[dict]:
    from tecdard.sim.backend import with_truth
    from tecdard.tools.demo import distance_to_axis
    from tests.test_ur_rotate import cutter_rig
    config = {} if accel_rad_s2 is None else {"robot.ur.accel_rad_s2": accel_rad_s2}
    out = []
    for seed in range(1, n + 1):
        with tempfile.TemporaryDirectory() as tmp, cutter_rig(pathlib.Path(tmp), seed, **config) as (fake, d):
            t0 = time.monotonic()
            reply = d.client.command("rotate", {"angle_deg": 30.0})
            ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 90.0)
            duration = time.monotonic() - t0
            ev = with_truth(ev, fake.truth())
        if ev["kind"] != "task_done":
            out.append({"seed": seed, "failed": ev.get("error", "?")})
            continue
        res, sim = ev["result"], ev["result"]["sim"]
        err = distance_to_axis(np.array(res["hinge"]["p"]), np.array(sim["hinge_point"]), np.array(sim["hinge_axis"]))
        out.append({"seed": seed, "hinge_mm": err * 1e3, "angle_deg": sim["angle_deg"],
                    "base_mm": sim["base_displacement"] * 1e3, "duration_s": duration})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rotates", type=int, default=5)
    args = ap.parse_args()
    s = stream(args.seconds)
    r = rotates(args.rotates)
    slow = rotates(3, accel_rad_s2=SLOW_ACCEL_RAD_S2)
    done = [x for x in r if "failed" not in x]
    lines = [
        f"# UR backend against the fake controller ({time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()})",
        "",
        "`python -m benchmarks.ur`: the real ur-rtde client (PyPI ur-rtde, in robots/ur_link.py's child "
        "process) against tests/fakes/fake_ur.py, a UR5e controller (PolyScope 5, 500 Hz) on loopback. "
        "The machine is shared; nothing here is a test.",
        "",
        f"## Link ({s['seconds']:.0f} s of speedJ at the 20 ms control tick)",
        "",
        "| figure | value |",
        "|---|---|",
        f"| controller states handed out | {s['state_hz']:.0f} per second (the controller's 500 Hz) |",
        f"| command latency, `command_joint_velocity` to the control script's registers | median "
        f"{s['lat_median_ms']:.2f} ms, p99 {s['lat_p99_ms']:.2f} ms, max {s['lat_max_ms']:.2f} ms "
        f"({s['seen']} of {s['commands']} commands seen) |",
        f"| first command from rest to the arm's first motion | {s['first_motion_ms']:.2f} ms |",
        f"| CPU, the link's child (ur-rtde's clients) | {100 * s['cpu_child']:.1f} % of a core |",
        f"| CPU, the daemon side (reader thread, 50 Hz commands) | {100 * s['cpu_self']:.1f} % of a core |",
        "",
        "The latency covers the pipe to the child, ur-rtde's speedJ (register writes over RTDE) and "
        "the wait for the next controller cycle that reads the registers (every 2 ms). The arm then ramps "
        "at speedJ's acceleration bound. Most of the child's CPU is ur-rtde's own: its receive interface "
        "alone, idle, took 15 % of a core on this machine (a thread that parses every 500 Hz package), "
        "and its control interface keeps a second RTDE connection.",
        "",
        f"## rotate, 30 deg, the paper cutter (hinge 15 cm from the TCP), {len(r)} runs",
        "",
        "| seed | hinge error (mm) | angle (deg) | base moved (mm) | task (s) |",
        "|---|---|---|---|---|",
    ]
    for x in r:
        if "failed" in x:
            lines.append(f"| {x['seed']} | failed: {x['failed']} | | | |")
        else:
            lines.append(f"| {x['seed']} | {x['hinge_mm']:.2f} | {x['angle_deg']:.2f} | {x['base_mm']:.2f} | "
                         f"{x['duration_s']:.1f} |")
    if done:
        lines += ["", f"Median hinge error {statistics.median(x['hinge_mm'] for x in done):.2f} mm, max "
                  f"{max(x['hinge_mm'] for x in done):.2f} mm (target < 5 mm); base moved at most "
                  f"{max(x['base_mm'] for x in done):.2f} mm (target < 2 mm)."]
    slow_done = [x for x in slow if "failed" not in x]
    lines += ["", f"With speedJ's acceleration bound at {SLOW_ACCEL_RAD_S2:g} rad/s^2 instead of the default "
              f"(robot.ur.accel_rad_s2), {len(slow)} runs: hinge error "
              + ", ".join(f"{x['hinge_mm']:.2f}" for x in slow_done) + " mm"
              + (f" ({len(slow) - len(slow_done)} failed)" if len(slow_done) < len(slow) else "")
              + ". The controller's ramp then lags the plan's joint rates and the soft grasp moves."]
    text = "\n".join(lines) + "\n"
    (ROOT / "benchmarks" / "ur.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
