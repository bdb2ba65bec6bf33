"""How lightly the daemon sits beside the arm (issue 37); writes benchmarks/footprint_runs.md.

    python -m benchmarks.footprint [--minutes M] [--paths sim,ur] [--load both|off|on] [--startup]

Each run: the daemon started, one rotate (a task's work done, the recorder's capture written), then
M minutes at rest, read every WINDOW_S:
- the control tick's lateness p99 over the window's own ticks (`late_ms_p99_recent`: the last 250
  ticks, 5 s) and the overruns;
- the daemon process's CPU, its children apart (the simulator, the UR link), and per OS thread;
- its RSS.
Paths: `sim`, the simulated robot (configs/sim.yaml); `ur`, the shape of a real rig: the UR backend
through ur-rtde against the fake controller (tests/fakes/fake_ur.py) whose arm is our simulator, and the
fingertip board on a pseudo-terminal. `--load on` runs a busy loop of its own at nice 0 beside it
(one core loaded). `--startup`: a warm start to READY (sd_notify) and to the first `status`, the
ahead-of-time kernel build, and `tecdard localize` through the CLI on a 1 s and an 11 s recording
(real time over the difference: the marginal speed).
The machine is shared: figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import os
import pathlib
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.ur import cpu_s  # noqa: E402
from tecdard.runtime.threads import read_threads_cpu_s  # noqa: E402
from tecdard.tools.demo import free_port  # noqa: E402
from tests.conftest import DaemonProcess, daemon_config  # noqa: E402

WINDOW_S = 5.0
WARM_UP_S = 60.0             # RSS growth is counted from this far into the rest
LOCALIZE_RUNS = 5            # the best of this many `tecdard localize` runs per recording (the machine is noisy)
OUT = ROOT / "benchmarks" / "footprint_runs.md"


def rss_mb(pid: int) -> float:
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


@contextlib.contextmanager
def rig(path: str, tmp: pathlib.Path, rt_priority: int | None = None):
    """(daemon) on the simulated robot, or on the UR backend with a board on a pty; with rt_priority,
    its control thread under SCHED_FIFO (control.rt_priority)."""
    extra = {} if rt_priority is None else {"control.rt_priority": rt_priority}
    if path == "sim":
        d = DaemonProcess(tmp, daemon_config(**extra))
        try:
            yield d
        finally:
            d.close()
    else:
        from tests.test_ur_rotate import cutter_rig
        with cutter_rig(tmp, 1, **extra) as (_, d):
            yield d


@contextlib.contextmanager
def core_load(on: bool):
    """A busy loop of its own at nice 0 (a second process loading one core)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if on else None
    try:
        yield
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()


def run(path: str, minutes: float, load: bool, rt_priority: int | None = None) -> dict:
    with tempfile.TemporaryDirectory() as tmp, rig(path, pathlib.Path(tmp), rt_priority) as d:
        reply = d.client.command("rotate", {"angle_deg": 20})
        done = d.client.wait_event(("task_done", "task_failed"), reply["task"], 120.0)
        time.sleep(2.0)
        pid = d.proc.pid
        with core_load(load):
            rss0, cpu0, th0, t0 = rss_mb(pid), cpu_s(pid), read_threads_cpu_s(f"/proc/{pid}/task"), time.monotonic()
            ctl0 = d.client.command("status")["state"]["control"]
            windows = []
            t_end = t0 + minutes * 60.0
            while time.monotonic() < t_end:
                time.sleep(WINDOW_S)
                ctl = d.client.command("status")["state"]["control"]
                windows.append((ctl.get("late_ms_p99_recent"), ctl.get("overruns"), rss_mb(pid)))
            span = time.monotonic() - t0
            th1 = read_threads_cpu_s(f"/proc/{pid}/task")
            out = {"path": path, "load": load, "minutes": minutes, "task": done["kind"],
                   "cpu_pct": 100.0 * (cpu_s(pid) - cpu0) / span, "rss0": rss0, "rss1": rss_mb(pid),
                   "rss_max": max(w[2] for w in windows), "late": [w[0] for w in windows if w[0] is not None],
                   # after a minute's warm-up (the "growth after warm-up"): the window nearest 60 s
                   "rss_warm": windows[min(len(windows) - 1, int(WARM_UP_S // WINDOW_S) - 1)][2],
                   "overruns": windows[-1][1] - ctl0.get("overruns", 0),
                   "threads": sorted(((n, 100.0 * (th1[n] - th0.get(n, 0.0)) / span) for n in th1),
                                     key=lambda x: -x[1]),
                   "status_threads": d.client.command("status")["state"].get("threads", {})}
    return out


@contextlib.contextmanager
def ready_listener(tmp: str, timeout_s: float = 60.0):
    """(NOTIFY_SOCKET's path, {"t": monotonic s of READY=1 once it came}, the listening thread)."""
    sock_path = os.path.join(tmp, "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    ready = {}

    def listen():
        sock.settimeout(timeout_s)
        with contextlib.suppress(OSError):
            while "t" not in ready:
                if b"READY=1" in sock.recv(4096):
                    ready["t"] = time.monotonic()
    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    try:
        yield sock_path, ready, listener
    finally:
        sock.close()


def wheel_first_start() -> float:
    """s from `tecdard run` to READY=1, the first start after `pip install` of a wheel built from this
    checkout (setup.py compiles the kernels into it), in a fresh venv whose dependencies are this one's."""
    from tests.conftest import dump_yaml
    from tests.test_install import checkout_copy, fresh_venv, pip
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        dist, src = tmp / "dist", checkout_copy(tmp / "src")
        subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(dist), str(src)],
                       check=True, capture_output=True)
        py = fresh_venv(tmp / "venv")
        pip(py, "--no-deps", str(next(dist.glob("tecdar-*.whl"))))
        cfg = daemon_config()
        cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
        cfg.setdefault("record", {})["dir"] = str(tmp / "recordings")
        (tmp / "tecdard.yaml").write_text(dump_yaml(cfg))
        with ready_listener(str(tmp), 300.0) as (sock_path, ready, listener):
            t0 = time.monotonic()
            proc = subprocess.Popen([str(py), "-m", "tecdard", "run", "--config", str(tmp / "tecdard.yaml")],
                                    cwd=tmp, env={**os.environ, "NOTIFY_SOCKET": sock_path},
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                listener.join(300.0)
            finally:
                proc.terminate()
                proc.wait(30)
        return ready.get("t", float("nan")) - t0


def warm_start() -> tuple[float, float]:
    """(s to READY=1 on NOTIFY_SOCKET, s to the first answered status) of a warm start."""
    with tempfile.TemporaryDirectory() as tmp, ready_listener(tmp) as (sock_path, ready, listener):
        t0 = time.monotonic()
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(), env={"NOTIFY_SOCKET": sock_path})
        try:
            d.client.command("status")
            t_status = time.monotonic() - t0
            listener.join(30.0)
        finally:
            d.close()
    return ready.get("t", float("nan")) - t0, t_status


def localize_speed() -> tuple[float, float, float]:
    """(s for a 1 s recording, s for an 11 s one, marginal x real time) through `tecdard localize`."""
    from tests.test_localize import scenario_file
    with tempfile.TemporaryDirectory() as tmp:
        took = []
        for rest_s, moving_s in ((0.5, 0.5), (0.5, 10.5)):
            rec = scenario_file(pathlib.Path(tmp) / f"r{moving_s}.npz", kind="edge-arc", seed=2,
                                duration_s=moving_s, rest_s=rest_s)
            best = float("inf")
            for _ in range(LOCALIZE_RUNS):
                t0 = time.monotonic()
                subprocess.run([sys.executable, "-m", "tecdard", "localize", str(rec), "--json"], check=True,
                               capture_output=True, cwd=ROOT)
                best = min(best, time.monotonic() - t0)
            took.append(best)
    return took[0], took[1], 10.0 / max(took[1] - took[0], 1e-9)


def aot_build_s() -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "tecdard.control.estimators.kernels.build", tmp], check=True,
                       capture_output=True, cwd=ROOT)
        return time.monotonic() - t0


def run_table(runs: list[dict]) -> list[str]:
    lines = ["| path | core loaded | idle CPU (children apart), % of a core | RSS after the rotate / max / end, MB "
             "| RSS growth after the first minute, MB | lateness p99 per 5 s window: min / median / max, ms "
             "| windows over 1 ms | overruns |",
             "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        late = sorted(r["late"])
        over = sum(x > 1.0 for x in late)
        lines.append(f"| {r['path']} | {'yes' if r['load'] else 'no'} | {r['cpu_pct']:.1f} | {r['rss0']:.0f} / "
                     f"{r['rss_max']:.0f} / {r['rss1']:.0f} | {r['rss1'] - r['rss_warm']:+.1f} | "
                     f"{late[0]:.2f} / {late[len(late) // 2]:.2f} / "
                     f"{late[-1]:.2f} | {over} of {len(late)} | {r['overruns']} |")
    return lines


def thread_table(runs: list[dict]) -> list[str]:
    names = collections.OrderedDict()
    for r in runs:
        for name, share in r["threads"]:
            if share >= 0.05:
                names[name] = True
    head = "| thread | " + " | ".join(f"{r['path']}{', loaded' if r['load'] else ''}" for r in runs) + " |"
    lines = [head, "|---|" + "---|" * len(runs)]
    for name in names:
        cells = [f"{dict(r['threads']).get(name, 0.0):.1f}" for r in runs]
        lines.append(f"| `{name}` | " + " | ".join(cells) + " |")
    waits = [", ".join(f"{n} {row.get('wake_ms_max')} ms" for n, row in r["status_threads"].items()
                       if row.get("wake_ms_max") is not None) for r in runs]
    lines.append("| largest wait to run once due (last 5 s, `status`) | " + " | ".join(waits) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="minutes at rest per run (default 10)")
    ap.add_argument("--paths", default="sim,ur", help="sim, ur or both (comma-separated)")
    ap.add_argument("--load", choices=("both", "off", "on"), default="both")
    ap.add_argument("--startup", action="store_true", help="also time start-up, the kernel build and localize")
    ap.add_argument("--rt", type=int, default=None, metavar="PRIORITY",
                    help="control.rt_priority for the runs (SCHED_FIFO; needs the privilege)")
    args = ap.parse_args()
    loads = {"both": (False, True), "off": (False,), "on": (True,)}[args.load]
    runs = [run(path, args.minutes, load, args.rt) for path in args.paths.split(",") for load in loads]
    lines = [f"# Footprint runs ({time.strftime('%Y-%m-%d %H:%M')}, {platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()})", "",
             f"`python -m benchmarks.footprint --minutes {args.minutes:g} --paths {args.paths} --load {args.load}"
             f"{' --startup' if args.startup else ''}{f' --rt {args.rt}' if args.rt else ''}`: after one rotate, {args.minutes:g} min at rest per run. "
             "The machine is shared; nothing here is a test.", "", *run_table(runs), "",
             "CPU per OS thread at rest, % of one core:", "", *thread_table(runs), ""]
    if args.startup:
        ready_s, status_s = warm_start()
        t1, t11, speed = localize_speed()
        build_s = aot_build_s()
        wheel_s = wheel_first_start()
        lines += ["| start-up and replay | value |", "|---|---|",
                  f"| warm start to READY=1 (sd_notify) | {ready_s:.2f} s |",
                  f"| warm start to the first answered `status` | {status_s:.2f} s |",
                  f"| the kernels' ahead-of-time build (`tecdard warm`'s compile) | {build_s:.0f} s |",
                  f"| the first start after installing a wheel, to READY=1 | {wheel_s:.2f} s |",
                  f"| `tecdard localize`, 1 s / 11 s recording | {t1:.2f} / {t11:.2f} s |",
                  f"| localize, marginal | {speed:.0f}x real time |", ""]
    OUT.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
