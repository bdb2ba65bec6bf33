"""Where the daemon's time and memory go at rest (issue 37, measuring before changing); writes
benchmarks/footprint_baseline.md.

    python -m benchmarks.footprint [--minutes M] [--window-s W]

The daemon on the simulated robot (configs/sim.yaml): started and timed to its first answered
`status` (a warm start, the kernel cache built), one `rotate` of 20 degrees, then idle for M minutes.
Every W seconds:
- the control tick's lateness p99 and overruns as `status` reports them (its statistics cover the
  last 1000 ticks, 20 s: a window's figure is the trailing 20 s, not W alone);
- the daemon process's CPU (the simulator's child apart) and each of its OS threads' CPU, by the
  name /proc gives them (Python's own threads all show the interpreter's name until they are named);
- its RSS.
The machine is shared: the figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import collections
import os
import pathlib
import platform
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.ur import CLK_TCK, cpu_s  # noqa: E402
from tests.conftest import DaemonProcess, daemon_config  # noqa: E402


def rss_mb(pid: int) -> float:
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per OS thread name (threads of one name summed)."""
    out: dict[str, float] = collections.defaultdict(float)
    for task in pathlib.Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            out[name] += (int(fields[11]) + int(fields[12])) / CLK_TCK
        except (FileNotFoundError, ProcessLookupError, IndexError):
            pass
    return dict(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--window-s", type=float, default=5.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        d = DaemonProcess(pathlib.Path(tmp), daemon_config())
        d.client.command("status")
        start_s = time.monotonic() - t0
        try:
            reply = d.client.command("rotate", {"angle_deg": 20})
            d.client.wait_event(("task_done", "task_failed"), reply["task"], 120.0)
            pid = d.proc.pid
            rss0, cpu0, th0, tw0 = rss_mb(pid), cpu_s(pid), threads_cpu_s(pid), time.monotonic()
            windows = []
            t_end = tw0 + args.minutes * 60.0
            while time.monotonic() < t_end:
                c, t = cpu_s(pid), time.monotonic()
                time.sleep(args.window_s)
                ctl = d.client.command("status")["state"]["control"]
                windows.append(((cpu_s(pid) - c) / (time.monotonic() - t), ctl.get("late_ms_p99"),
                                ctl.get("overruns"), rss_mb(pid)))
            span = time.monotonic() - tw0
            th1 = threads_cpu_s(pid)
            cpu_share = (cpu_s(pid) - cpu0) / span
            rss1 = rss_mb(pid)
        finally:
            d.close()
    late = [w[1] for w in windows if isinstance(w[1], (int, float))]
    per_thread = sorted(((name, (th1.get(name, 0.0) - th0.get(name, 0.0)) / span) for name in th1),
                        key=lambda x: -x[1])
    lines = [
        f"# The daemon at rest, before issue 37's changes ({time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()})", "",
        f"`python -m benchmarks.footprint --minutes {args.minutes:g}`: the simulated robot, one rotate of 20 deg, "
        f"then {args.minutes:g} min idle in {args.window_s:g} s windows. The machine is shared; nothing here is a "
        "test.", "",
        "| figure | value |", "|---|---|",
        f"| start to the first answered `status` (warm) | {start_s:.1f} s |",
        f"| daemon CPU idle (its children apart), share of one core | {100 * cpu_share:.1f} % |",
        f"| RSS after the rotate / at the end | {rss0:.0f} / {rss1:.0f} MB |",
        f"| tick lateness p99 over the windows (trailing 20 s each): min / median / max | "
        f"{min(late):.2f} / {sorted(late)[len(late) // 2]:.2f} / {max(late):.2f} ms |" if late else "| lateness | - |",
        f"| overruns at the end | {windows[-1][2] if windows else '-'} |", "",
        "## CPU per OS thread, idle (share of one core)", "",
        "| thread (/proc comm) | CPU |", "|---|---|",
        *[f"| `{name}` | {100 * share:.2f} % |" for name, share in per_thread if share >= 0.0005], "",
    ]
    text = "\n".join(lines)
    (ROOT / "benchmarks" / "footprint_baseline.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
