"""The fleet's figures (issue 38): the `contact` message's latency from a daemon to a client one and two routers
away on mutual TLS with the roster's ACL, upload throughput and the daemon's added CPU while uploading, and
query time over an index of 10 000 synthetic episodes. Writes benchmarks/fleet.md.

    .venv/bin/python -m benchmarks.fleet [--episodes 10000] [--uploads 12]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.api.session import TlsFiles, session_config  # noqa: E402
from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.tools.demo import free_port  # noqa: E402
from benchmarks.__main__ import proc_cpu_s  # noqa: E402

OUT = ROOT / "benchmarks" / "fleet.md"
ROSTER = {"robots": ["arm-a", "arm-b"], "routers": ["router-1", "router-2"], "operators": {"alice": ["*"]}}
CONTACT_BYTES = 420          # a contact message's size on the wire (JSON), about
PROBES = 2000                # synthetic contact messages per latency run
PROBE_RATE_HZ = 200.0        # the estimator's output rate
QUERIES = {
    "episodes and contacts per robot": "SELECT robot, count(*), sum(contacts) FROM episodes GROUP BY robot",
    "eta per robot per week": "SELECT robot, date_trunc('week', start_time) AS w, avg(eta) FROM episodes GROUP BY ALL",
    "contacts whose sigma never fell under 2 mm": "SELECT count(*) FROM contacts WHERE sigma_m >= 0.002",
    "convergence p90 per robot (join)": "SELECT e.robot, quantile_cont(c.converged_after_s, 0.9) FROM contacts c "
                                        "JOIN episodes e USING (id) GROUP BY e.robot",
}


def pki(folder: pathlib.Path):
    from tests.fakes.certs import ScratchCA
    ca = ScratchCA(folder)
    return ca, {cn: ca.issue(cn) for cn in ("arm-a", "arm-b", "router-1", "router-2", "alice")}


def files(ca, ident) -> TlsFiles:
    return TlsFiles(str(ca.path), str(ident.cert), str(ident.key))


def start_router(folder: pathlib.Path, name: str, ca, ident, roster: pathlib.Path, connect=()):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    cfg = folder / f"{name}.yaml"
    cfg.write_text(dump_yaml({"zenoh": {"listen": [endpoint], "connect": list(connect),
                                        "tls": {"ca": str(ca.path), "cert": str(ident.cert), "key": str(ident.key)}},
                              "access_control": {"roster": str(roster)}}))
    log = open(folder / f"{name}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "router", "--config", str(cfg)], stdout=log,
                            stderr=subprocess.STDOUT, cwd=ROOT)
    deadline = time.monotonic() + 30.0
    while "listening on" not in (folder / f"{name}.log").read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError((folder / f"{name}.log").read_text())
        time.sleep(0.05)
    return proc, endpoint


def client_session(endpoint: str, tls: TlsFiles):
    import zenoh
    conf = session_config([], [endpoint], tls=tls, mode="client")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def stats_ms(x) -> str:
    x = np.asarray(x) * 1e3
    return (f"{np.percentile(x, 50):.2f} / {np.percentile(x, 90):.2f} / {np.percentile(x, 99):.2f} / {x.max():.2f}"
            if len(x) else "-")


def mesh_latency(folder: pathlib.Path, ca, ids, r1: str, r2: str) -> dict[str, list[float]]:
    """Synthetic contact messages from arm-a's certificate on router-1, received by alice on router-1 (one
    router away) and on router-2 (two routers away): latency by the host's monotonic clock, s."""
    got = {"one router": [], "two routers": []}
    with client_session(r1, files(ca, ids["arm-a"])) as pub_s, \
            client_session(r1, files(ca, ids["alice"])) as near, client_session(r2, files(ca, ids["alice"])) as far:
        for name, sess in (("one router", near), ("two routers", far)):
            sess.declare_subscriber("tecdar/arm-a/contact",
                                    lambda s, name=name: got[name].append(
                                        time.perf_counter_ns() - json.loads(s.payload.to_string())["sent_ns"]))
        pub = pub_s.declare_publisher("tecdar/arm-a/contact")
        time.sleep(1.5)
        pad = "x" * (CONTACT_BYTES - 40)
        t_next = time.monotonic()
        for _ in range(PROBES):
            pub.put(json.dumps({"sent_ns": time.perf_counter_ns(), "pad": pad}))
            t_next += 1.0 / PROBE_RATE_HZ
            time.sleep(max(0.0, t_next - time.monotonic()))
        time.sleep(0.5)
    return {k: [v * 1e-9 for v in vals] for k, vals in got.items()}


def daemon_latency(folder: pathlib.Path, ca, ids, r1: str, r2: str) -> dict[str, list[float]]:
    """A sim daemon (arm-a, client of router-1) rotates 20 deg; its contact messages' arrival at alice on
    router-1 and on router-2 less their own time `t` (the estimate's sample, the host's monotonic clock), s."""
    from tests.conftest import daemon_config
    cfg = daemon_config(**{"robot.name": "arm-a", "zenoh.tls": {"ca": str(ca.path), "cert": str(ids["arm-a"].cert),
                                                                 "key": str(ids["arm-a"].key)}})
    cfg["zenoh"].pop("listen", None)
    cfg["zenoh"].update(mode="client", connect=[r1])
    cfg.setdefault("record", {})["dir"] = str(folder / "rec-lat")
    path = folder / "arm-a.yaml"
    path.write_text(dump_yaml(cfg))
    log = open(folder / "arm-a.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", str(path)], stdout=log,
                            stderr=subprocess.STDOUT, cwd=ROOT)
    got = {"one router": [], "two routers": []}
    try:
        near = Client(r1, robot="arm-a", tls=files(ca, ids["alice"]), daemon_name="router-1")
        far = Client(r2, robot="arm-a", tls=files(ca, ids["alice"]), daemon_name="router-2")
        far.wait_alive(120.0)
        subs = []
        for name, cli in (("one router", near), ("two routers", far)):
            if not cli.connect(10.0):
                raise RuntimeError(f"no session through {name}")
            subs.append(cli.session.declare_subscriber("tecdar/arm-a/contact", lambda s, name=name: got[name].append(
                time.monotonic() - json.loads(s.payload.to_string())["t"])))
        reply = far.command("rotate", {"angle_deg": 20.0})
        far.wait_event(("task_done", "task_failed"), reply["task"], 120.0)
        time.sleep(0.5)
        for sub in subs:
            sub.undeclare()
        near.close()
        far.close()
    finally:
        proc.terminate()
        proc.wait(10)
    return got


def upload_figures(folder: pathlib.Path, n: int, src: pathlib.Path, mcap: bool) -> dict:
    """A sim daemon finds `n` copies of the recording `src` in its record dir at start and uploads them
    (with their MCAP, or not) to a file:// store: throughput, and its CPU while uploading against at rest
    afterwards."""
    from tests.conftest import daemon_config
    from tecdard.fleet.episodes import EpisodeStore, StoreParams
    tag = "mcap" if mcap else "plain"
    rec_dir = folder / f"rec-up-{tag}"
    rec_dir.mkdir()
    for k in range(n):
        shutil.copy(src, rec_dir / f"20261204-10{k:04d}-rotate-{k:08x}.npz")
    total_mb = sum(f.stat().st_size for f in rec_dir.glob("*.npz")) / 1e6
    store_dir = folder / f"store-up-{tag}"
    cfg = daemon_config(**{"store": {"url": f"file://{store_dir}", "mcap": mcap}, "record.dir": str(rec_dir)})
    path = folder / f"up-{tag}.yaml"
    path.write_text(dump_yaml(cfg))
    endpoint = cfg["zenoh"]["listen"][0]
    log = open(folder / f"up-{tag}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", str(path)], stdout=log,
                            stderr=subprocess.STDOUT, cwd=ROOT)
    try:
        with Client(endpoint, robot="sim") as cli:
            cli.wait_alive(120.0)
            t0, c0 = time.monotonic(), proc_cpu_s(proc.pid)
            overruns0 = cli.command("status")["state"]["control"]["overruns"]
            late = []
            while len(list(rec_dir.glob("*.uploaded"))) < n:
                if time.monotonic() - t0 > 600:
                    raise RuntimeError("uploads did not finish in 10 minutes")
                control = cli.command("status")["state"]["control"]
                late.append(control.get("late_ms_p99_recent") or 0.0)
                time.sleep(0.5)
            t1, c1 = time.monotonic(), proc_cpu_s(proc.pid)
            worker_s = sum(proc_cpu_s(pid) for pid in _children(proc.pid) if _comm(pid) == "tecdar-upload")
            overruns = cli.command("status")["state"]["control"]["overruns"] - overruns0
            time.sleep(20.0)
            t2, c2 = time.monotonic(), proc_cpu_s(proc.pid)
            threads = cli.command("status")["state"].get("threads") or {}
    finally:
        proc.terminate()
        proc.wait(10)
    stored_mb = sum(f.stat().st_size for f in store_dir.rglob("*") if f.is_file()) / 1e6
    assert len(list(store_dir.glob("sim/*/*.npz"))) == n
    return {"n": n, "mb": total_mb, "stored_mb": stored_mb, "s": t1 - t0, "cpu_up": 100 * (c1 - c0) / (t1 - t0),
            "cpu_rest": 100 * (c2 - c1) / (t2 - t1), "store": EpisodeStore(StoreParams(url=f"file://{store_dir}")),
            "rec_s": _duration_s(src), "threads": threads, "late_max_ms": max(late, default=0.0),
            "overruns": overruns, "worker_pct": 100 * worker_s / (t1 - t0), "worker_s": worker_s}


def _children(pid: int) -> list[int]:
    out = []
    for task in pathlib.Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _comm(pid: int) -> str:
    try:
        return pathlib.Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def _duration_s(path) -> float:
    from tecdard.recording.format import load_recording
    rec = load_recording(path)
    return float(rec.imu_t[-1] - rec.imu_t[0])


def _one_daemon_recording(folder: pathlib.Path) -> pathlib.Path:
    """A daemon recording of a 20 deg rotate on the simulated cutter."""
    from tests.conftest import daemon_config
    rec_dir = folder / "rec-src"
    cfg = daemon_config(**{"record.enabled": True, "record.dir": str(rec_dir)})
    path = folder / "src.yaml"
    path.write_text(dump_yaml(cfg))
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", str(path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        with Client(cfg["zenoh"]["listen"][0], robot="sim") as cli:
            cli.wait_alive(120.0)
            reply = cli.command("rotate", {"angle_deg": 20.0})
            cli.wait_event(("task_done", "task_failed"), reply["task"], 120.0)
            cli.wait_event(("recording_written",), None, 60.0)
    finally:
        proc.terminate()
        proc.wait(10)
    return next(rec_dir.glob("*.npz"))


def synthetic_index(store, n: int, robots: int = 8) -> float:
    """n synthetic episodes (one contact each), one index file per episode as the uploader writes them;
    the seconds it took."""
    from tecdard.fleet.episodes import CONTACT_COLUMNS, EPISODE_COLUMNS, parquet_bytes
    rng = np.random.default_rng(38)
    t0 = time.monotonic()
    start = datetime.datetime(2026, 1, 5, tzinfo=datetime.timezone.utc)
    for k in range(n):
        robot = f"arm-{k % robots}"
        name = f"synthetic-{k:06d}"
        when = start + datetime.timedelta(minutes=53 * k)
        ep_id = f"{robot}/{name}"
        sigma = float(rng.lognormal(np.log(0.002), 0.6))
        row = {"id": ep_id, "robot": robot, "episode": name, "start_time": when, "day": when.date(),
               "task": f"t{k}", "verb": "rotate", "backend": "ur", "config_digest": "0" * 16,
               "eta": float(rng.normal(2.0, 0.1)), "duration_s": 3.0, "result": "done", "contacts": 1,
               "npz_key": f"{robot}/{when.date()}/{name}.npz", "bytes": 1_500_000, "uploaded_at": when}
        contact = {"id": ep_id, "robot": robot, "episode": name, "n": 0, "onset_t": 1.0, "onset_time": when,
                   "x_m": float(rng.normal(0.4, 0.1)), "y_m": 0.0, "z_m": 0.2, "sigma_m": sigma,
                   "converged_after_s": float(rng.uniform(0.02, 0.2)), "uploaded_at": when}
        store.put_once(f"index/contacts/{robot}/{name}.parquet", parquet_bytes(CONTACT_COLUMNS, [contact]))
        store.put_once(f"index/episodes/{robot}/{name}.parquet", parquet_bytes(EPISODE_COLUMNS, [row]))
    return time.monotonic() - t0


def time_queries(store, repeats: int = 3) -> dict[str, float]:
    from tecdard.fleet.index import Index, query
    out = {}
    for name, sql in QUERIES.items():
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            query(Index(store), sql)
            best = min(best, time.perf_counter() - t0)
        out[name] = best
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=10000, help="synthetic episodes in the index (default 10000)")
    ap.add_argument("--uploads", type=int, default=12, help="recordings the daemon uploads (default 12)")
    ap.add_argument("--parts", default="mesh,upload,query", help="which figures (comma-separated)")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    from tecdard.fleet.episodes import EpisodeStore, StoreParams
    from tecdard.fleet.index import compact
    lines = ["# The fleet's figures (issue 38)", "",
             f"Measured {datetime.date.today()} on {platform.machine()}, {os.cpu_count()} cores, Linux "
             f"{platform.release()}, Python {platform.python_version()}; the machine is shared and noisy. "
             "Reproduce: `.venv/bin/python -m benchmarks.fleet`.", ""]
    with tempfile.TemporaryDirectory(prefix="tecdar-fleet-bench-") as tmp:
        folder = pathlib.Path(tmp)
        if "mesh" in parts:
            ca, ids = pki(folder)
            roster = folder / "roster.yaml"
            roster.write_text(dump_yaml(ROSTER))
            p1, r1 = start_router(folder, "router-1", ca, ids["router-1"], roster)
            p2, r2 = start_router(folder, "router-2", ca, ids["router-2"], roster, connect=[r1])
            try:
                synth = mesh_latency(folder, ca, ids, r1, r2)
                live = daemon_latency(folder, ca, ids, r1, r2)
            finally:
                for p in (p2, p1):
                    p.terminate()
                    p.wait(10)
            lines += ["## Mesh latency of `contact` (mutual TLS, the roster's ACL, two `tecdard router`s)", "",
                      f"Synthetic: {PROBES} messages of {CONTACT_BYTES} bytes at {PROBE_RATE_HZ:.0f} Hz from robot "
                      "arm-a's certificate on router-1, received by an operator on router-1 (one router away) and on "
                      "router-2 (two routers away), by the host's clock. Daemon: a simulated arm's contact estimates "
                      "during a 20 deg rotate, from the estimate's own time (its IMU sample) to the client.", "",
                      "| path | messages | p50 / p90 / p99 / max, ms |", "|---|---|---|"]
            for name in ("one router", "two routers"):
                lines.append(f"| synthetic, {name} | {len(synth[name])} | {stats_ms(synth[name])} |")
            for name in ("one router", "two routers"):
                lines.append(f"| daemon's contact, {name} | {len(live[name])} | {stats_ms(live[name])} |")
        if "upload" in parts:
            src = _one_daemon_recording(folder)
            ups = [upload_figures(folder, args.uploads, src, mcap) for mcap in (True, False)]
            up = ups[0]
            lines += ["", "## Upload", "",
                      f"A simulated daemon finds {up['n']} copies of its recording of a 20 deg rotate "
                      f"({up['rec_s']:.1f} s, {up['mb'] / up['n']:.2f} MB each) in its record.dir at start and uploads "
                      "them with their index rows to a file:// store, with `store.mcap` (each recording replayed and "
                      "written as MCAP beside it) and without. CPU: the daemon process (its children apart: the "
                      "simulator, the upload process), from its start of uploading to the last, against 20 s at rest "
                      "after; the upload process's own below.", "",
                      "| figure | with MCAP | without |", "|---|---|---|",
                      "| stored | " + " | ".join(f"{u['stored_mb']:.1f} MB" for u in ups) + " |",
                      "| time to upload all | " + " | ".join(f"{u['s']:.1f} s" for u in ups) + " |",
                      "| throughput | " + " | ".join(f"{u['mb'] / u['s']:.2f} MB/s of recordings, {u['n'] / u['s']:.2f} "
                                                      "episodes/s" for u in ups) + " |",
                      "| daemon CPU while uploading | " + " | ".join(f"{u['cpu_up']:.1f} % of a core" for u in ups) + " |",
                      "| daemon CPU at rest after | " + " | ".join(f"{u['cpu_rest']:.1f} %" for u in ups) + " |",
                      "| added while uploading | " + " | ".join(f"{u['cpu_up'] - u['cpu_rest']:.1f} % of a core"
                                                             for u in ups) + " |",
                      "| the upload process (tecdar-upload, nice +10), CPU | " + " | ".join(
                          f"{u['worker_s']:.1f} s, {u['worker_pct']:.0f} % of a core while uploading" for u in ups)
                      + " |",
                      "| the tick's lateness p99 over 5 s, the largest seen while uploading; overruns | " +
                      " | ".join(f"{u['late_max_ms']:.2f} ms; {u['overruns']}" for u in ups) + " |", ""]
        if "query" in parts:
            store = EpisodeStore(StoreParams(url=f"file://{folder}/synthetic"))
            t_write = synthetic_index(store, args.episodes)
            loose = time_queries(store)
            t0 = time.monotonic()
            compact(store)
            t_compact = time.monotonic() - t0
            packed = time_queries(store)
            lines += ["## Query time over the index", "",
                      f"{args.episodes} synthetic episodes over 8 robots, one contact each, written as the uploader "
                      f"writes them (one file per episode and table: {t_write:.0f} s), then compacted "
                      f"(`tecdard episodes compact`, {t_compact:.1f} s). Best of 3, in process (DuckDB).", "",
                      f"| query | {args.episodes} files per table, s | compacted, s |", "|---|---|---|"]
            for name in QUERIES:
                lines.append(f"| {name} | {loose[name]:.2f} | {packed[name]:.3f} |")
    if parts >= {"mesh", "upload", "query"}:
        OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
