"""The daemon under a query flood (issue 16): CPU shares, IMU staleness, a rotate, and stop's reply
time, with and without the flood; writes benchmarks/hostile.md.

    python -m benchmarks.hostile [--runs N]
"""
from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.tools.demo import distance_to_axis, free_port, start_daemon, stop_daemon  # noqa: E402
from tests.conftest import sim_config  # noqa: E402

WINDOW_S = 5.0
FLOOD_NICE = 19
ZENOH_THREADS = ("rx", "tx", "net", "acc", "app")


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds per thread name group (main, zenoh, python) of a process."""
    hz = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for task in pathlib.Path(f"/proc/{pid}/task").glob("*"):
        try:
            stat = (task / "stat").read_text()
            name = stat[stat.index("(") + 1:stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2:].split()
            cpu = (int(fields[11]) + int(fields[12])) / hz
        except (OSError, ValueError, IndexError):
            continue
        group = "main" if int(task.name) == pid else "zenoh" if name.split("-")[0] in ZENOH_THREADS else "python"
        out[group] = out.get(group, 0.0) + cpu
    return out


def process_cpu(pid: int) -> float:
    hz = os.sysconf("SC_CLK_TCK")
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / hz


def shares(pid: int, child: int, seconds: float) -> dict[str, float]:
    """Percent of a core per group over `seconds`."""
    a, ca = thread_cpu(pid), process_cpu(child)
    time.sleep(seconds)
    b, cb = thread_cpu(pid), process_cpu(child)
    out = {k: (b.get(k, 0.0) - a.get(k, 0.0)) / seconds * 100 for k in b}
    out["sim child"] = (cb - ca) / seconds * 100
    return out


def stop_reply_s(cli, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.monotonic()
        assert cli.command("stop", timeout=10.0)["ok"] is True
        out.append(time.monotonic() - t0)
        time.sleep(0.1)
    return out


def one_run(flood: bool) -> dict:
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="tecdar-bench-hostile-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = sim_config(**{"zenoh.listen": [endpoint], "map.output_dir": str(tmp / "maps")})
    (tmp / "cfg.yaml").write_text(dump_yaml(cfg))
    log = open(tmp / "daemon.log", "w")
    proc = start_daemon(str(tmp / "cfg.yaml"), endpoint, log)
    flooder = None
    try:
        with Client(endpoint) as cli:
            cli.wait_alive(300.0)
            time.sleep(2.0)
            child = int(subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "spawn_main"], capture_output=True,
                                       text=True).stdout.split()[0])
            if flood:
                flooder = subprocess.Popen(["nice", "-n", str(FLOOD_NICE), sys.executable, "-m", "tests.fakes.flood",
                                            endpoint, "600"], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                                           env={**os.environ, "PYTHONPATH": str(ROOT)})
                time.sleep(1.0)
            cpu = shares(proc.pid, child, WINDOW_S)
            reply = cli.command("rotate", {"angle_deg": 30.0})
            ev = cli.wait_event(("task_done", "task_failed"), reply["task"], 120.0) if reply.get("ok") else None
            err = None
            if ev is not None and ev["kind"] == "task_done":
                res = ev["result"]
                err = distance_to_axis(np.array(res["hinge"]["p"]), np.array(res["sim"]["hinge_point"]),
                                       np.array(res["sim"]["hinge_axis"]))
            stops = stop_reply_s(cli, 5)
            faults = [e for e in cli.event_log if e["kind"] == "fault"]
    finally:
        sent = None
        if flooder is not None:
            flooder.terminate()
            out, _ = flooder.communicate(timeout=10)
            sent = int(out.strip() or 0)
        stop_daemon(proc)
        log.close()
    return {"cpu": cpu, "rotate": None if ev is None else ev["kind"], "hinge_err_mm": None if err is None else err * 1e3,
            "stop_s": stops, "faults": [f["code"] for f in faults], "sent": sent}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=2)
    args = ap.parse_args(argv)
    rows = {False: [], True: []}
    for k in range(args.runs):
        for flood in (False, True):
            r = one_run(flood)
            rows[flood].append(r)
            print(f"run {k + 1} {'flood' if flood else 'quiet'}: {r}", flush=True)
    lines = ["# The daemon under a query flood", "",
             "`python -m benchmarks.hostile` (issue 16). A daemon on `configs/sim.yaml`; the flood is",
             "`tests/fakes/flood.py` at nice 19: bursts of 3000 `status` queries (junk and oversized payloads",
             "among them) and four 10 MB payloads, every 0.25 s, never waiting for a reply. CPU in % of one",
             f"core over {WINDOW_S:g} s before the rotate; stop: the reply time of five stops sent at rest.", "",
             "| run | queries sent | daemon main | daemon Python threads | Zenoh threads | sim child | rotate | hinge error | stop reply, median (max) | faults |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for flood in (False, True):
        for r in rows[flood]:
            c = r["cpu"]
            err = "-" if r["hinge_err_mm"] is None else f"{r['hinge_err_mm']:.2f} mm"
            stop = f"{statistics.median(r['stop_s']) * 1e3:.0f} ms ({max(r['stop_s']) * 1e3:.0f} ms)"
            lines.append(f"| {'flood' if flood else 'quiet'} | {r['sent'] or 0} | {c.get('main', 0):.1f} % | "
                         f"{c.get('python', 0):.1f} % | {c.get('zenoh', 0):.1f} % | {c['sim child']:.1f} % | "
                         f"{r['rotate']} | {err} | {stop} | {', '.join(r['faults']) or 'none'} |")
    lines += ["", f"Machine: {os.cpu_count()} cores, measured {time.strftime('%Y-%m-%d')}.", ""]
    (ROOT / "benchmarks" / "hostile.md").write_text("\n".join(lines))
    print("wrote benchmarks/hostile.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
