"""Start-up times of `tecdard run` on the simulated robot (issue 17); writes benchmarks/startup.md.

    python -m benchmarks.startup [--runs N] [--cold]

Time from spawning `tecdard run` to its liveliness token (READY: threads running, the IMU's onset
warm-up done), seen by a client polling every 50 ms:
- first start: the first start after `make install` (the kernel cache warmed by `tecdard warm`)
  with the operating system's page cache dropped where this user may (else: the first start of this
  run, which is as cold as the files are);
- warm start: each start after that;
- with `--cold`, one start with an empty NUMBA_CACHE_DIR: what a start that must compile costs.
Targets (issue 17): first start <= 5 s, warm <= 3 s.
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

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.tools.demo import free_port, stop_daemon  # noqa: E402
from tests.conftest import sim_config  # noqa: E402

FIRST_TARGET_S, WARM_TARGET_S = 5.0, 3.0


def drop_page_cache() -> bool:
    try:
        os.sync()
        pathlib.Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def ready_line_s(log: pathlib.Path, t_spawn_wall: float) -> float:
    """Seconds from spawn to the daemon's own "tecdard ready" log line (its asctime, ms)."""
    import datetime
    for line in log.read_text().splitlines():
        if "tecdard ready" in line:
            stamp = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            return stamp - t_spawn_wall
    return float("nan")


def one_start(tmp: pathlib.Path, env: dict | None = None, timeout: float = 300.0) -> tuple[float, float]:
    """(seconds to the client's first sight of the liveliness token, seconds to the ready log line)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = sim_config(**{"zenoh.listen": [endpoint], "map.output_dir": str(tmp / "maps")})
    path = tmp / "startup.yaml"
    path.write_text(dump_yaml(cfg))
    with Client(endpoint) as cli:
        t0, t0_wall = time.monotonic(), time.time()
        proc = subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", str(path)], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=open(tmp / "startup.log", "w"),
                                env={**os.environ, **(env or {})})
        try:
            cli.wait_alive(timeout, running=lambda: proc.poll() is None)
            seen = time.monotonic() - t0
        finally:
            stop_daemon(proc)
    return seen, ready_line_s(tmp / "startup.log", t0_wall)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--cold", action="store_true", help="also one start with an empty kernel cache")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        dropped = drop_page_cache()
        first = one_start(tmp)
        warm = [one_start(tmp) for _ in range(args.runs)]
        cold = None
        if args.cold:
            cold = one_start(tmp, env={"NUMBA_CACHE_DIR": str(tmp / "empty-cache")})
    lines = [
        "# Start-up times (`python -m benchmarks.startup`)",
        "",
        f"`tecdard run` on configs/sim.yaml, spawn to liveliness token (READY), on {os.cpu_count()} cores.",
        "",
        "The daemon's own READY is its `tecdard ready` log line; a client sees the token up to one",
        "connect retry (0.1-0.5 s) later.",
        "",
        "| start | READY, s | seen by a client, s | target |",
        "|---|---|---|---|",
        f"| first after `make install` ({'page cache dropped' if dropped else 'page cache as found'}) "
        f"| {first[1]:.2f} | {first[0]:.2f} | <= {FIRST_TARGET_S:g} |",
        f"| warm, median of {len(warm)} | {statistics.median(w[1] for w in warm):.2f} (max "
        f"{max(w[1] for w in warm):.2f}) | {statistics.median(w[0] for w in warm):.2f} | <= {WARM_TARGET_S:g} |",
    ]
    if cold is not None:
        lines.append(f"| empty kernel cache (compiles) | {cold[1]:.1f} | {cold[0]:.1f} | (said in the log's first line) |")
    lines.append("")
    out = "\n".join(lines)
    print(out)
    (ROOT / "benchmarks" / "startup.md").write_text(out)
    print("wrote benchmarks/startup.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
