"""franky-sim for the Franka backend's tests: libfranka's own protocol over MuJoCo physics, on loopback.

`python -m tests.franka_sim --host 127.0.0.x` runs franky-sim's server (PyPI franky-sim, the
`franka-sim` extra) with one FR3 and its hand, on that address (the robot's port 1337 and the
hand's 1338 are fixed, so each server gets an address of its own), and prints `READY <host>` once
it listens. The simulation steps on an absolute 1 kHz schedule (franky-sim's own loop sleeps a
fixed 1 ms after each step's work and runs at 0.7-0.9x real time on 2 cores); steps it cannot
keep up with are counted and the schedule moves on rather than bursting.

Options for the tests:
- `--reply-version N` / `--reply-status incompatible`: the robot server answers libfranka's
  Connect with this version, or with franka's "incompatible library version" status;
- `--silent`: a server that accepts the connection and never answers (what an older libfranka
  meets, and franky.Robot() then waits for ever);
- `--joint7-kv`: joint 7's velocity gain (franky-sim's default 200 makes it chatter).

`ServerProcess` starts one and waits for READY; `close()` ends it; `kill()` ends it as a crash would.
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

ROBOT_PORT, GRIPPER_PORT = 1337, 1338
STEP_S = 0.001
RESYNC_BEHIND_S = 0.05          # further behind than this, the schedule restarts from now
JOINT7_KV = 40.0


def free_franka_host() -> str:
    """A 127.0.0.x address whose robot and hand ports are free."""
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        try:
            for port in (ROBOT_PORT, GRIPPER_PORT):
                with socket.create_server((host, port)):
                    pass
            return host
        except OSError:
            continue
    raise RuntimeError("no free 127.0.0.x address for franky-sim")


def _silent(host: str) -> None:
    """Accept on the robot's port and never answer."""
    srv = socket.create_server((host, ROBOT_PORT))
    print(f"READY {host}", flush=True)
    held = []
    while True:
        conn, _ = srv.accept()
        held.append(conn)


def _patch_connect_reply(version: int, status: str) -> None:
    """The robot server's Connect reply, as a robot of another system version gives it."""
    from franky_sim import franka_server as fs

    def handle(self, server, command_type_struct: str = "I"):
        header = fs.MessageHeader(self.command_type, self.command_id, 8)
        code = fs.ConnectStatus.kIncompatibleLibraryVersion if status == "incompatible" else fs.ConnectStatus.kSuccess
        self.client_socket.sendall(header.to_bytes(command_type_struct=command_type_struct)
                                   + struct.pack("<HH4x", code.value, version))
        if status != "incompatible":
            server._setup_udp_connection(self.network_udp_port)
    fs.ConnectCommand.handle = handle


def run(args) -> None:
    if args.silent:
        _silent(args.host)
        return
    if args.reply_version is not None or args.reply_status != "ok":
        _patch_connect_reply(10 if args.reply_version is None else args.reply_version, args.reply_status)
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MUJOCO_DEFAULT_KV, MujocoSimulator
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    kv = tuple(MUJOCO_DEFAULT_KV[:6]) + (args.joint7_kv,)
    with MujocoSimulator() as sim:
        sim.add_robot(kv=kv)
        with SimulationServer(sim, hostname_candidates=[args.host]) as server:
            print(f"READY {args.host}", flush=True)
            next_t = time.monotonic()
            behind = 0
            while not stop.is_set():
                server.run_once(realtime=False)
                next_t += STEP_S
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -RESYNC_BEHIND_S:
                    behind += 1
                    next_t = time.monotonic()


class ServerProcess:
    """franky-sim in a child process on a free loopback address."""

    def __init__(self, *extra: str, host: str | None = None, ready_s: float = 60.0):
        self.host = host or free_franka_host()
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.franka_sim", "--host", self.host, *extra],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        self.output: list[str] = []
        ready = threading.Event()

        def drain():
            for line in self.proc.stdout:
                self.output.append(line.rstrip())
                if line.startswith(f"READY {self.host}"):
                    ready.set()
        threading.Thread(target=drain, daemon=True).start()
        if not ready.wait(ready_s):
            self.kill()
            raise RuntimeError(f"franky-sim did not start on {self.host}: {self.output[-5:]}")

    def kill(self) -> None:
        """End it as a crash would: no goodbye on any socket."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", required=True)
    ap.add_argument("--reply-version", type=int, default=None)
    ap.add_argument("--reply-status", choices=("ok", "incompatible"), default="ok")
    ap.add_argument("--silent", action="store_true")
    ap.add_argument("--joint7-kv", type=float, default=JOINT7_KV)
    run(ap.parse_args())


if __name__ == "__main__":
    main()
