"""`make bench`: estimator speed and whole-daemon accuracy/CPU on the simulated robot; writes benchmarks/RESULTS.md."""
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

from control.conditioning import GyroConditioner  # noqa: E402
from control.ekf import ContactEKF, EkfParams  # noqa: E402
from control.onset import OnsetDetector  # noqa: E402
from control.pipeline import ContactPipeline  # noqa: E402
from tecdard.client import Client  # noqa: E402
from tecdard.demo import distance_to_axis, free_port, start_daemon, stop_daemon  # noqa: E402

ODR_HZ = 6667.0
CLK_TCK = os.sysconf("SC_CLK_TCK")


def bench_ekf_step(n: int = 20000) -> dict:
    rng = np.random.default_rng(0)
    ekf = ContactEKF(EkfParams())
    ekf.start(np.zeros(3), np.array([0, 0, 0.02]))
    w = rng.normal(0, 0.1, (n, 3))
    z = rng.normal(0, 1e-3, (n, 3))
    times = np.empty(n)
    dt = 1 / ODR_HZ
    for k in range(n):
        t0 = time.perf_counter()
        ekf.step(dt, w[k], z[k], z[k])
        times[k] = time.perf_counter() - t0
    return {"median_us": float(np.median(times) * 1e6), "p99_us": float(np.percentile(times, 99) * 1e6)}


def bench_pipeline(seconds: float = 1.0) -> dict:
    """Real-time factor of the whole contact pipeline on a tracked contact (worst case: EKF every sample)."""
    n = int(seconds * ODR_HZ)
    t = np.arange(n) / ODR_HZ
    rng = np.random.default_rng(1)
    gyro = rng.normal(0, 5e-3, (n, 3)) + [0, -0.066, 0]
    accel = np.tile([0, 0, 9.81], (n, 1)) + rng.normal(0, 0.03, (n, 3))
    accel[700:760] += [2.0, 0, 0]
    pipe = ContactPipeline(OnsetDetector(0.4, warmup_s=0.05), GyroConditioner(np.eye(3), 2.0, lpf_window=33),
                           EkfParams())
    for tp in np.arange(0, seconds, 1 / 65):
        pipe.add_proprio(tp, np.array([0.3, 0, 0.5]) + [0, 0, 0.02 * tp], np.array([0, 0, 0.02]), np.eye(3),
                         np.zeros(3))
    batch = np.column_stack([t, gyro, accel])
    t0 = time.perf_counter()
    for k in range(0, n, 64):
        pipe.process(batch[k:k + 64])
    el = time.perf_counter() - t0
    return {"seconds": seconds, "wall_s": el, "realtime_factor": seconds / el}


def proc_cpu_s(pid: int) -> float:
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def bench_rotate(radius: float, seed: int, strategy: str = "arc", angle_deg: float = 30.0) -> dict:
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["sim"]["seed"] = seed
    cfg["sim"]["hinge"]["point"] = [0.307 - radius, 0.0, 0.487]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "bench.yaml"
        path.write_text(yaml.safe_dump(cfg))
        with open(pathlib.Path(tmp) / "log", "w") as log:
            proc = start_daemon(str(path), endpoint, log)
            try:
                with Client(endpoint) as cli:
                    cli.wait_alive(60)
                    time.sleep(1.0)
                    cpu_idle0, t_idle0 = proc_cpu_s(proc.pid), time.monotonic()
                    time.sleep(2.0)
                    cpu_idle = (proc_cpu_s(proc.pid) - cpu_idle0) / (time.monotonic() - t_idle0)
                    cpu0, t0 = proc_cpu_s(proc.pid), time.monotonic()
                    reply = cli.command("rotate", {"angle_deg": angle_deg, "strategy": strategy})
                    ev = cli.wait_event(("task_done", "task_failed"), reply["task"], 120)
                    cpu_task = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
                    state = cli.command("status")["state"]
                    t_sig = time.monotonic()
            finally:
                code = stop_daemon(proc)
                exit_s = time.monotonic() - t_sig if "t_sig" in locals() else float("nan")
    if ev["kind"] != "task_done":
        return {"radius": radius, "seed": seed, "strategy": strategy, "failed": ev.get("error")}
    res = ev["result"]
    sim = res["sim"]
    return {
        "radius": radius, "seed": seed, "strategy": strategy,
        "hinge_err_mm": distance_to_axis(np.array(res["hinge"]["p"]), np.array(sim["hinge_point"]),
                                         np.array(sim["hinge_axis"])) * 1e3,
        "angle_err_deg": sim["angle_deg"] - angle_deg,
        "base_mm": sim["base_displacement"] * 1e3,
        "cpu_idle": cpu_idle, "cpu_task": cpu_task,
        "ticks": state["control"], "exit_code": code, "exit_s": exit_s,
    }


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks")
    ap.add_argument("--quick", action="store_true", help="one daemon run per strategy")
    args = ap.parse_args()
    lines = [f"# Benchmarks ({time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()})", ""]
    ekf = bench_ekf_step()
    pipe = bench_pipeline()
    lines += ["## Estimator", "",
              f"- EKF step (9-state, 3D, numpy): median {ekf['median_us']:.1f} us, p99 {ekf['p99_us']:.1f} us",
              f"- Contact pipeline while tracking (trigger + conditioning + EKF every sample): "
              f"{pipe['realtime_factor']:.1f}x real time ({pipe['wall_s'] * 1e3:.0f} ms for {pipe['seconds']:.0f} s at 6667 Hz)",
              ""]
    print("\n".join(lines), flush=True)
    runs = []
    cases = [(0.15, 1, "arc"), (0.15, 1, "straight")] if args.quick else \
        [(r, s, "arc") for r in (0.10, 0.15, 0.20, 0.25) for s in (1, 2)] + [(0.15, 1, "straight"), (0.20, 2, "straight")]
    for radius, seed, strategy in cases:
        r = bench_rotate(radius, seed, strategy)
        runs.append(r)
        print(r, flush=True)
    lines += ["## Whole daemon, `rotate` 30 deg on the simulated paper cutter", "",
              "| radius | seed | strategy | hinge error | angle error | base moved | CPU idle | CPU during task | ticks | overruns | tick work p99 | lateness p99 | exit after SIGTERM |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        if "failed" in r:
            lines.append(f"| {r['radius'] * 100:.0f} cm | {r['seed']} | {r['strategy']} | failed: {r['failed']} |||||||||")
            continue
        tk = r["ticks"]
        lines.append(f"| {r['radius'] * 100:.0f} cm | {r['seed']} | {r['strategy']} | {r['hinge_err_mm']:.2f} mm | "
                     f"{r['angle_err_deg']:+.2f} deg | {r['base_mm']:.2f} mm | {r['cpu_idle'] * 100:.0f} % | "
                     f"{r['cpu_task'] * 100:.0f} % | {tk.get('ticks')} | {tk.get('overruns')} | "
                     f"{tk.get('work_ms_p99')} ms | {tk.get('late_ms_p99')} ms | {r['exit_s'] * 1e3:.0f} ms |")
    arc = [r for r in runs if r.get("strategy") == "arc" and "failed" not in r]
    if arc:
        lines += ["", f"Arc runs: hinge error median {statistics.median(r['hinge_err_mm'] for r in arc):.2f} mm, "
                      f"max {max(r['hinge_err_mm'] for r in arc):.2f} mm; base displacement max "
                      f"{max(r['base_mm'] for r in arc):.2f} mm. CPU is the daemon process (all threads), "
                      f"100 % = one core."]
    out = ROOT / "benchmarks" / "RESULTS.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"\nwritten {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
