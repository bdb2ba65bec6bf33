"""`make bench`: whole-daemon accuracy, CPU and ticks on the simulated robot; writes benchmarks/daemon.md."""
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
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.tools.demo import distance_to_axis, free_port, start_daemon, stop_daemon  # noqa: E402

ODR_HZ = 6667.0
RADII = (0.10, 0.15, 0.20, 0.25)
PAPER_PATH_M = 0.15          # the paper's cutter experiment: a gripper path of 15 cm
REACH_MAX_DEG = 70.0         # at 10 cm the Panda's elbow (joint 4) reaches its limit near 75 deg from this home pose
CLK_TCK = os.sysconf("SC_CLK_TCK")


def proc_cpu_s(pid: int) -> float:
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def children_cpu_s(pid: int) -> float:
    """CPU time of a process's live children (the simulation process), s."""
    total = 0.0
    for task in pathlib.Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            try:
                total += proc_cpu_s(int(child))
            except FileNotFoundError:
                pass
    return total


HOME_TCP = np.array([0.307, 0.0, 0.487])   # the TCP at configs/sim.yaml's home pose
POSES = ("behind, axis y", "handle 20 deg up", "axis yawed 30 deg", "beside, axis x")


def hinge_pose(name: str, radius: float) -> dict:
    """Where the simulated cutter's hinge is, `radius` from the TCP at home."""
    tcp = HOME_TCP
    if name == "behind, axis y":
        return {"point": (tcp - [radius, 0.0, 0.0]).tolist(), "axis": [0.0, 1.0, 0.0]}
    if name == "handle 20 deg up":       # the handle rises 20 deg from the hinge to the TCP
        e = np.radians(20.0)
        return {"point": (tcp - radius * np.array([np.cos(e), 0.0, np.sin(e)])).tolist(), "axis": [0.0, 1.0, 0.0]}
    if name == "axis yawed 30 deg":
        y = np.radians(30.0)
        return {"point": (tcp - radius * np.array([np.cos(y), -np.sin(y), 0.0])).tolist(),
                "axis": [float(np.sin(y)), float(np.cos(y)), 0.0]}
    if name == "beside, axis x":
        return {"point": (tcp - [0.0, radius, 0.0]).tolist(), "axis": [1.0, 0.0, 0.0]}
    raise ValueError(f"unknown hinge pose {name!r}")


def probe_direction(name: str, radius: float, off_deg: float = 0.0) -> list[float]:
    """The handle's tangent at the grasp, upwards (what Algorithm 2 of the paper probes along), tilted
    `off_deg` outwards along the handle: an operator's error in `direction`."""
    h = hinge_pose(name, radius)
    e0 = HOME_TCP - np.array(h["point"])
    e0 /= np.linalg.norm(e0)
    t = np.cross(np.array(h["axis"]), e0)
    t = t if t[2] >= 0 else -t
    off = np.radians(off_deg)
    return [float(x) for x in np.cos(off) * t + np.sin(off) * e0]


def bench_rotate(radius: float, seed: int, strategy: str = "arc", angle_deg: float = 30.0,
                 turn_tool: bool = True, pose: str = POSES[0], off_deg: float = 0.0, pose_spec: dict | None = None,
                 direction: list | None = None) -> dict:
    """One `rotate` on the simulated cutter, its hinge at a named pose (or at `pose_spec`: point and
    axis), probing along `direction` (default: the named pose's tangent, `off_deg` off it)."""
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["sim"]["seed"] = seed
    cfg["sim"]["hinge"].update(pose_spec or hinge_pose(pose, radius))
    if direction is None:
        direction = probe_direction(pose, radius, off_deg)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "bench.yaml"
        path.write_text(dump_yaml(cfg))
        with open(pathlib.Path(tmp) / "log", "w") as log:
            proc = start_daemon(str(path), endpoint, log)
            try:
                with Client(endpoint) as cli:
                    cli.wait_alive(60)
                    time.sleep(1.0)
                    cpu_idle0, t_idle0 = proc_cpu_s(proc.pid), time.monotonic()
                    time.sleep(2.0)
                    cpu_idle = (proc_cpu_s(proc.pid) - cpu_idle0) / (time.monotonic() - t_idle0)
                    cpu0, sim0, t0 = proc_cpu_s(proc.pid), children_cpu_s(proc.pid), time.monotonic()
                    reply = cli.command("rotate", {"angle_deg": angle_deg, "strategy": strategy,
                                                   "turn_tool": turn_tool,
                                                   "direction": direction})
                    ev = cli.wait_event(("task_done", "task_failed"), reply["task"], 120)
                    cpu_task = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
                    cpu_sim = (children_cpu_s(proc.pid) - sim0) / (time.monotonic() - t0)
                    state = cli.command("status")["state"]
                    t_sig = time.monotonic()
            finally:
                code = stop_daemon(proc)
                exit_s = time.monotonic() - t_sig if "t_sig" in locals() else float("nan")
    if strategy == "arc" and not turn_tool:
        strategy = "arc, tool held"
    pose = pose if not off_deg else f"{pose}, probe {off_deg:g} deg off the tangent"
    if ev["kind"] != "task_done":
        base = ev.get("sim", {}).get("base_displacement", float("nan"))
        return {"radius": radius, "seed": seed, "strategy": strategy, "angle_deg": angle_deg,
                "pose": pose, "failed": ev.get("error"), "base_mm": base * 1e3}
    res = ev["result"]
    sim = res["sim"]
    return {
        "radius": radius, "seed": seed, "strategy": strategy, "angle_deg": angle_deg, "pose": pose,
        "hinge_err_mm": distance_to_axis(np.array(res["hinge"]["p"]), np.array(sim["hinge_point"]),
                                         np.array(sim["hinge_axis"])) * 1e3,
        "angle_err_deg": sim["angle_deg"] - angle_deg,
        "base_mm": sim["base_displacement"] * 1e3,
        "slip_deg": abs(sim.get("grasp_slip_deg", 0.0)),
        "cpu_idle": cpu_idle, "cpu_task": cpu_task, "cpu_sim": cpu_sim,
        "ticks": state["control"], "exit_code": code, "exit_s": exit_s,
    }


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks")
    ap.add_argument("--quick", action="store_true", help="one daemon run per strategy")
    args = ap.parse_args()
    lines = [f"# Benchmarks ({time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()})", ""]
    lines += ["Estimator accuracy and speed: [README.md](README.md); serial driver: [serial.md](serial.md).", ""]
    print("\n".join(lines), flush=True)
    runs = []
    # (radius, seed, strategy, angle, hinge pose, probe direction error): 30 deg at every radius; the
    # paper's cutter run, a gripper path of 15 cm (the angle that makes the arc 15 cm long), by arc
    # and by straight pull; other hinge poses; a probe direction off the tangent; the tool held
    paper = [(r, 1, s, round(min(np.degrees(PAPER_PATH_M / r), REACH_MAX_DEG), 1), POSES[0], 0.0) for r in RADII
             for s in ("arc", "straight")]
    poses = [(r, 1, "arc", 30.0, pose, 0.0) for pose in POSES[1:] for r in (0.10, 0.25)]
    cases = [(0.15, 1, "arc", 30.0, POSES[0], 0.0), (0.15, 1, "straight", 30.0, POSES[0], 0.0)] if args.quick else \
        [(r, s, "arc", 30.0, POSES[0], 0.0) for r in RADII for s in (1, 2)] + paper + poses + \
        [(r, 1, "arc", 30.0, POSES[1], off) for off in (5.0, 10.0, -10.0) for r in (0.10, 0.25)] + \
        [(0.15, 1, "held", 30.0, POSES[0], 0.0)]
    for radius, seed, strategy, angle, pose, off in cases:
        r = bench_rotate(radius, seed, "arc" if strategy == "held" else strategy, angle,
                         turn_tool=strategy != "held", pose=pose, off_deg=off)
        runs.append(r)
        print(r, flush=True)
    lines += ["## Whole daemon, `rotate` on the simulated paper cutter", "",
              "| hinge pose | radius | seed | strategy | angle | hinge error | angle error | base moved | grasp slip | CPU idle | CPU during task | simulation CPU during task | ticks | overruns | tick work p99 | lateness p99 | exit after SIGTERM |",
              "|" + "---|" * 17]
    for r in runs:
        if "failed" in r:
            # 17 cells, as the header: the failure in the hinge error's, the base's where it goes
            cells = [r['pose'], f"{r['radius'] * 100:.0f} cm", str(r['seed']), r['strategy'], f"{r['angle_deg']:g} deg",
                     f"failed: {r['failed']}", "-", f"{r['base_mm']:.2f} mm"] + ["-"] * 9
            lines.append("| " + " | ".join(cells) + " |")
            continue
        tk = r["ticks"]
        lines.append(f"| {r['pose']} | {r['radius'] * 100:.0f} cm | {r['seed']} | {r['strategy']} | {r['angle_deg']:g} deg | {r['hinge_err_mm']:.2f} mm | "
                     f"{r['angle_err_deg']:+.2f} deg | {r['base_mm']:.2f} mm | {r['slip_deg']:.1f} deg | "
                     f"{r['cpu_idle'] * 100:.0f} % | "
                     f"{r['cpu_task'] * 100:.0f} % | {r['cpu_sim'] * 100:.0f} % | {tk.get('ticks')} | {tk.get('overruns')} | "
                     f"{tk.get('work_ms_p99')} ms | {tk.get('late_ms_p99')} ms | {r['exit_s'] * 1e3:.0f} ms |")
    arc = [r for r in runs if r.get("strategy") == "arc" and "failed" not in r and "off the tangent" not in r["pose"]]
    if arc:
        lines += ["", f"Arc runs probing along the tangent, every hinge pose: hinge error median {statistics.median(r['hinge_err_mm'] for r in arc):.2f} mm, "
                      f"max {max(r['hinge_err_mm'] for r in arc):.2f} mm; base displacement max "
                      f"{max(r['base_mm'] for r in arc):.2f} mm. CPU is the daemon process (all threads), "
                      f"100 % = one core; the simulated arm, world and IMU run in a child process, whose "
                      f"CPU is the simulation column.",
              "", "The tool turns with the arc (`turn_tool`, default). The simulated fingertips twist up to "
                  "10 deg relative to the gripper, then slip: with the tool held (`arc, tool held`) the "
                  "grasp slips once the handle has turned past that; the IMU then stops following the handle, "
                  "and the divergence stop ends the task.",
              "", "The straight pull (`strategy: straight`) goes as far as the arc would, along the arc's first "
                  "tangent: the handle end then leaves the circle by r (sqrt(1 + theta^2) - 1), which the "
                  "cutter's base absorbs. At 30 deg that is 0.13 r (13 mm at 10 cm, under 20 mm below 15.5 cm); "
                  "over the paper's 15 cm gripper path (its Case 2; at 10 cm radius 70 deg, 12 cm, as the Panda's elbow "
                  "reaches its limit near 75 deg there) it is 41-62 mm. A pull that drags the base hard ends "
                  "in a protective stop on force (15 N) or tracking; the base moved is then where it stopped. "
                  "With the default divergence stop (`control.max_nis_ratio` 10) the pull ends earlier: as "
                  "the handle end leaves the circle the contact model stops fitting, and the innovations pass "
                  "10x their expected size before the base has moved 2 mm (the daemon test raises the limit "
                  "to show the drag).",
              "", "Hinge poses: the cutter behind the gripper with its axis along y (the default), its handle rising "
                  "20 deg from the hinge, its axis yawed 30 deg, beside the gripper with its axis along x. Every run "
                  "probes along the handle's tangent at the grasp (`direction`), as Algorithm 2 of the paper "
                  "does. Off the tangent the grasp absorbs the probe's component along the handle, the "
                  "estimate takes that for rotation about another centre; the arc's radial admittance (grasp force) "
                  "keeps the base still, and the rows 'probe N deg off the tangent' measure what the estimate keeps."]
    out = ROOT / "benchmarks" / "daemon.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"\nwritten {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
