"""`make run`: start tecdard on the simulated robot, rotate the paper cutter over Zenoh, print what happened."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys

import numpy as np

from tecdard.api.client import Client, ClientError


# A start waits while the daemon process runs, up to: (a loaded 2-core machine compiles in 50-90 s)
WARM_START_BUDGET_S = 60.0
COLD_START_BUDGET_S = 300.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def distance_to_axis(p: np.ndarray, point: np.ndarray, axis: np.ndarray) -> float:
    """Distance (m) from p to the line through `point` along unit `axis`."""
    d = p - point
    return float(np.linalg.norm(d - np.dot(d, axis) * axis))


def start_daemon(config: str, endpoint: str, log_file=None) -> subprocess.Popen:
    """The daemon in a session of its own: a Ctrl-C at the terminal reaches the demo alone, which cancels
    its task and then stops the daemon, rather than the daemon's shutdown failing the task under it."""
    return subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", config, "--listen", endpoint],
                            stdout=log_file or subprocess.DEVNULL, stderr=log_file or subprocess.DEVNULL,
                            start_new_session=True)


def stop_daemon(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()
    return proc.returncode


def startup_budget_s() -> tuple[float, str]:
    """How long a start may take here, and why: a cold kernel cache compiles (tecdard.kernel_cache)."""
    from tecdard.tools import kernel_cache
    try:
        cache = kernel_cache.state()
    except Exception:
        cache = None
    if cache is not None and cache.warm:
        return WARM_START_BUDGET_S, "a warm start takes about 3 s"
    return COLD_START_BUDGET_S, (f"this first start compiles the estimator's kernels, about "
                                 f"{kernel_cache.COLD_COMPILE_S:.0f} s on 2 cores")


def _rotate(cli: Client, proc: subprocess.Popen, angle_deg: float) -> tuple[dict, dict] | None:
    """Wait for the daemon, rotate, wait for the end: the end event and the status after it. A Ctrl-C
    meanwhile cancels the task (the daemon brakes the arm) and answers None, having said so."""
    budget_s, why = startup_budget_s()
    task = None
    try:
        print(f"waiting for the daemon to be ready (its liveliness token tecdar/sim/alive); {why}", flush=True)
        cli.wait_alive(budget_s, running=lambda: proc.poll() is None,
                       waiting=lambda s: s >= 1.0 and print(f"  still waiting, {s:.0f} s so far (up to "
                                                            f"{budget_s:.0f} s)", flush=True))
        reply = cli.command("rotate", {"angle_deg": angle_deg})
        if not reply.get("ok"):
            raise ClientError(f"rotate refused: {reply['error']['code']}: {reply['error']['message']}")
        task = reply["task"]
        print(f"rotate {angle_deg:g} deg accepted as task {task}; waiting ...", flush=True)
        ev = cli.wait_event(("task_done", "task_failed"), task, timeout=120.0)
        return ev, cli.command("status")
    except KeyboardInterrupt:
        if task is None:
            print("demo: interrupted; nothing was started", flush=True)
            return None
        try:
            cli.command("cancel", {"task": task}, timeout=5.0)
            ended = cli.wait_event(("task_done", "task_failed"), task, timeout=10.0)
            print(f"demo: interrupted; task {task} cancelled ({ended['kind']})", flush=True)
        except (ClientError, KeyboardInterrupt):
            print(f"demo: interrupted; task {task} may still be running: the daemon is stopped next, "
                  f"which stops the arm", flush=True)
        return None


def run_demo(config: str, angle_deg: float) -> int:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    print(f"starting tecdard on {config} at {endpoint} ...", flush=True)
    log_path = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"tecdard-demo-{os.getpid()}.log")
    with open(log_path, "w") as log_file:
        proc = start_daemon(config, endpoint, log_file)
        try:
            with Client(endpoint) as cli:
                ran = _rotate(cli, proc, angle_deg)
        except ClientError as exc:
            print(f"demo failed: {exc} (daemon log: {log_path})")
            log_file.flush()
            with open(log_path, errors="replace") as f:
                tail = f.read()[-2000:].strip()
            if tail:
                print(tail)
            return 1
        finally:
            code = stop_daemon(proc)
    if ran is None:
        print(f"daemon exit     {code} (log: {log_path})")
        return 130
    ev, status = ran
    if ev["kind"] != "task_done":
        print(f"task failed: {ev.get('error')} (daemon log: {log_path})")
        return 1
    res = ev["result"]
    truth = res["sim"]
    p_est = np.array(res["hinge"]["p"])
    err = distance_to_axis(p_est, np.array(truth["hinge_point"]), np.array(truth["hinge_axis"]))
    ticks = status["state"]["control"]
    print("")
    print(f"hinge estimate  {np.round(p_est * 1e3, 1).tolist()} mm  (one-sigma {np.round(np.array(res['hinge']['std']) * 1e3, 1).tolist()} mm)")
    print(f"hinge truth     {np.round(np.array(truth['hinge_point']) * 1e3, 1).tolist()} mm, axis {np.round(truth['hinge_axis'], 3).tolist()}")
    print(f"hinge error     {err * 1e3:.2f} mm from the true axis")
    print(f"angle reached   {truth['angle_deg']:.2f} deg true, {res['angle_deg']:.2f} deg estimated (asked {angle_deg:g})")
    print(f"base displaced  {truth['base_displacement'] * 1e3:.2f} mm")
    print(f"control ticks   {ticks.get('ticks')} ticks, {ticks.get('overruns')} overruns, work p50 {ticks.get('work_ms_p50')} ms"
          f" p99 {ticks.get('work_ms_p99')} ms max {ticks.get('work_ms_max')} ms, lateness p99 {ticks.get('late_ms_p99')} ms")
    print(f"daemon exit     {code} (log: {log_path})")
    return 0 if code == 0 else 1


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="start the daemon on the simulated robot and rotate the paper cutter")
    from tecdard import shipped
    p.add_argument("--config", default=str(shipped.config("sim.yaml")),
                   help="the daemon's config (default: the shipped sim.yaml, %(default)s)")
    p.add_argument("--angle", type=float, default=30.0, help="rotation, degrees")
    p.set_defaults(func=lambda args: run_demo(args.config, args.angle))
