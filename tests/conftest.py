"""Shared fixtures: temporary configs, a tecdard subprocess on a free loopback port, a Zenoh client."""
from __future__ import annotations

import contextlib
import copy
import importlib.abc
import importlib.machinery
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest
import yaml

from tecdard.api.client import Client
from tecdard.tools.demo import distance_to_axis, free_port
from tecdard.config import dump_yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
# a developer's shell may point the command line at their own daemon: never the tests'
for _name in ("TECDAR_CONNECT", "TECDAR_ROBOT"):
    os.environ.pop(_name, None)
SIM_CONFIG = ROOT / "configs" / "sim.yaml"
DAEMON_START_TIMEOUT_S = 60.0
HANG_DUMP_S = 3.0            # a daemon that outlives its SIGTERM: this long to write its threads' stacks
# The folders that install under tecdard (pyproject's package-dir). From the checkout they are also
# importable by their bare names, and a test that did so would pass here and fail on a wheel.
CHECKOUT_ONLY_ROOTS = ("control", "drivers", "robots", "sim", "ros2")


class _BareNames(importlib.abc.MetaPathFinder):
    """Refuses `import control` (and the rest) from the checkout: ours is `tecdard.control`."""

    def find_spec(self, name, path=None, target=None):
        if path is None and name in CHECKOUT_ONLY_ROOTS:
            spec = importlib.machinery.PathFinder.find_spec(name)
            if spec is not None and spec.origin and pathlib.Path(spec.origin).resolve().is_relative_to(ROOT):
                raise ImportError(f"{name}: installed as tecdard.{name}; import it by that name")
        return None


sys.meta_path.insert(0, _BareNames())


LEFT_THREADS_JOIN_S = 5.0     # after the last test, how long threads that are not daemon threads may take to end
_exit_status = [0]


def pytest_sessionfinish(session, exitstatus):
    _exit_status[0] = int(exitstatus)


def pytest_unconfigure(config):
    """A thread that is not a daemon thread and outlives the run keeps the interpreter from exiting:
    CI once sat 70 minutes after the summary (a Zenoh callback thread). Such a run says which threads,
    in one line, and exits with a failure instead of hanging. The controller removes the run's locks."""
    import shutil
    import threading
    import time
    for folder in _locks_made:
        shutil.rmtree(folder, ignore_errors=True)
    deadline = time.monotonic() + LEFT_THREADS_JOIN_S
    left = [t for t in threading.enumerate() if not t.daemon and t is not threading.main_thread()]
    for t in left:
        t.join(max(deadline - time.monotonic(), 0.0))
    left = [t.name for t in left if t.is_alive()]
    if left:
        sys.stdout.flush()
        sys.stderr.write(f"tests: threads that are not daemon threads outlived the run, which would never "
                         f"exit: {', '.join(left)}\n")
        sys.stderr.flush()
        os._exit(_exit_status[0] or 1)


# The whole-daemon tests run the simulated arm (1 kHz physics and the IMU at 6.7 kHz, a process of
# its own), the daemon and the test's client on this machine's 2 shared cores. There IMU samples
# now and then reach the daemon's ring 51-68 ms late (8 stale-IMU stops in 7 fresh-clone runs of
# the suite, about 270 whole-daemon tests), and on CI (2026-12-02) a 104 ms IMU gap under a flood
# and a 100 ms gap in joint commands ended two tasks under test. Tests that are not about those
# stops allow 0.2 s of IMU silence and 0.25 s without a joint command before the simulated arm
# stops itself; the stale-IMU tests set the product's 50 ms, the simulator's own tests its 0.1 s.
TEST_IMU_STALE_S = 0.2
TEST_SIM_COMMAND_TIMEOUT_S = 0.25
# Likewise the divergence stop: while a task goes as planned the smoothed NIS ratio reads under 2,
# under 4 with the other core busy, but a map probe on CI's loaded machine read 10.08 once against
# the product's limit of 10 (the divergence test sets that; a slipping grasp reads 25-32).
TEST_MAX_NIS_RATIO = 20.0
# The robot's states come from the same simulator process as the IMU's samples and meet the same
# stalls: tests that are not about the stale-state stop allow 0.25 s (the product's: a real arm
# 50 ms, the simulator 100 ms; robots.backend.RobotBackend.STATE_AGE_S).
TEST_STATE_AGE_S = 0.25
STILL_M = 2e-4               # the TCP has not moved (encoder noise is ~0.03 mm)
# the allowances above as a test's daemon takes them (dotted config paths)
TEST_ALLOWANCES = {"control.imu_stale_s": TEST_IMU_STALE_S, "sim.robot.command_timeout_s": TEST_SIM_COMMAND_TIMEOUT_S,
                   "control.max_nis_ratio": TEST_MAX_NIS_RATIO, "robot.max_state_age_s": TEST_STATE_AGE_S}


def tcp_now(cli) -> np.ndarray:
    return np.array(cli.command("status")["state"]["tcp"]["p"])


def tecdard(*args, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """The command line, `python -m tecdard ARGS...`, run from the checkout."""
    return subprocess.run([sys.executable, "-m", "tecdard", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def daemon_config(**overrides) -> dict:
    """configs/sim.yaml with the allowances above for a test's daemon, listening on a free port (never
    the default 7507, where a developer's own daemon may run), and `overrides` (sim_config's)."""
    return sim_config(**{"zenoh.listen": [f"tcp/127.0.0.1:{free_port()}"], **TEST_ALLOWANCES, **overrides})


def sim_config(**overrides) -> dict:
    """configs/sim.yaml as a dict with dotted-path overrides, e.g. {"sim.seed": 3}; `...` deletes a key."""
    cfg = copy.deepcopy(yaml.safe_load(SIM_CONFIG.read_text()))
    for dotted, value in overrides.items():
        node = cfg
        *path, last = dotted.split(".")
        for key in path:
            node = node.setdefault(key, {})
        if value is ...:
            node.pop(last, None)
        else:
            node[last] = value
    return cfg


class DaemonProcess:
    def __init__(self, tmp_path: pathlib.Path, cfg: dict, env: dict | None = None, client_tls=None, protocol="tcp",
                 router: str | None = None, endpoint: str | None = None, node_name: str | None = None,
                 own_group: bool = False):
        """`router`: the daemon runs as a Zenoh client of the router at that endpoint, listening on
        nothing, and the test's client reaches it through the router. `endpoint`: where it listens
        (default: `protocol` on a free loopback port). `node_name`: with TLS, the certificate name the
        test's client expects of the node it connects to (default the daemon's, DAEMON_NAME). `own_group`: the
        daemon leads a process group of its own, which a test signals as a terminal does (`os.killpg`)."""
        cfg = copy.deepcopy(cfg)
        if router is None:
            self.endpoint = endpoint or f"{protocol}/127.0.0.1:{free_port()}"
            cfg["zenoh"]["listen"] = [self.endpoint]
        else:
            self.endpoint = router
            cfg["zenoh"].pop("listen", None)
            cfg["zenoh"].update(mode="client", connect=[router])
        cfg.setdefault("map", {}).setdefault("output_dir", str(tmp_path / "maps"))    # never into the checkout
        cfg.setdefault("record", {}).setdefault("dir", str(tmp_path / "recordings"))
        self.config_path = tmp_path / "tecdard.yaml"
        self.config_path.write_text(dump_yaml(cfg))
        self.log_path = tmp_path / "tecdard.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "tecdard", "run", "--config", str(self.config_path)],
                                     stdout=self._log, stderr=subprocess.STDOUT, cwd=ROOT,
                                     env=None if env is None else {**os.environ, **env}, start_new_session=own_group)
        self.client = Client(self.endpoint, robot=cfg["robot"]["name"], tls=client_tls,
                             **({} if node_name is None else {"daemon_name": node_name}))
        try:
            self.client.wait_alive(DAEMON_START_TIMEOUT_S, running=lambda: self.proc.poll() is None)
        except Exception as exc:
            self.close()
            raise RuntimeError(f"tecdard did not come up ({exc}): {self.log()}") from None

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def terminate(self, sig=signal.SIGTERM, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                # where it hangs, in its log (the daemon's faulthandler), before it is killed
                self.proc.send_signal(signal.SIGABRT)
                try:
                    self.proc.wait(HANG_DUMP_S)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        return self.proc.returncode

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            self.terminate()
            self._log.close()


@pytest.fixture(autouse=True)
def frozen_heap():
    """What the runner holds before a test is frozen out of the garbage collector's way for the test
    (gc.freeze, as the daemon does after its start): late in the suite the runner holds some 800 MB,
    and a full collection over it stalled the test's own real-time threads (a board's stream on a pty,
    a fake controller) by hundreds of ms. Freezing and unfreezing are list splices, not scans."""
    import gc
    gc.freeze()
    yield
    gc.unfreeze()


LOCKS_ENV = "TECDAR_TEST_LOCKS"     # the run's folder of locks, made by the controller, named to its workers
_locks_made: list[str] = []


def pytest_configure(config):
    """The controller makes the run's folder of locks before it starts its workers, which inherit its name."""
    if not os.environ.get("PYTEST_XDIST_WORKER") and LOCKS_ENV not in os.environ:
        os.environ[LOCKS_ENV] = tempfile.mkdtemp(prefix="tecdar-tests-")
        _locks_made.append(os.environ[LOCKS_ENV])


def _run_lock_file(name: str):
    return open(pathlib.Path(os.environ[LOCKS_ENV]) / f"{name}.lock", "a+")


@contextlib.contextmanager
def run_lock(name: str, shared: bool = False):
    """Across the workers of one run (`make test` runs the suite on pytest-xdist's workers), a lock by
    name: a build in the checkout (the firmware's make) made by one worker at a time. Serial runs take
    none. Writers first: every taker passes a gate one at a time, and an exclusive one holds the gate
    until it has the lock, so the shared takers that keep overlapping one another cannot starve it (with
    plain flock, a test marked `alone` once waited 221 s on three workers)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    import fcntl
    with _run_lock_file(name + "-gate") as gate, _run_lock_file(name) as lock:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(autouse=True)
def cores_shared(request):
    """On the workers, a test marked `alone` (one that judges a simulator's or an emulator's timing, which the
    other workers' load would starve, or one that reinstalls the running venv) has the machine to itself:
    it takes the run's `machine` lock exclusively, every other test takes it shared."""
    with run_lock("machine", shared=request.node.get_closest_marker("alone") is None):
        yield


@pytest.fixture(scope="session", autouse=True)
def default_endpoint_taken():
    """The default endpoint is held for the whole run, as a developer's own daemon would hold it: a
    test that starts a daemon or a client on it fails here every time, not only on their machine.
    Where something already holds it, that something is the decoy."""
    import socket
    from tecdard.api.session import DEFAULT_ENDPOINT
    host, _, port = DEFAULT_ENDPOINT.removeprefix("tcp/").rpartition(":")
    decoy = socket.socket()
    try:
        decoy.bind((host, int(port)))
        decoy.listen()
    except OSError:
        decoy.close()
        decoy = None
    yield
    if decoy is not None:
        decoy.close()


@pytest.fixture
def make_daemon(tmp_path):
    started = []

    def factory(env: dict | None = None, client_tls=None, protocol="tcp", router=None, endpoint=None,
                node_name=None, **overrides) -> DaemonProcess:
        sub = tmp_path / f"d{len(started)}"
        sub.mkdir()
        d = DaemonProcess(sub, daemon_config(**overrides), env, client_tls=client_tls, protocol=protocol,
                          router=router, endpoint=endpoint, node_name=node_name)
        started.append(d)
        return d

    yield factory
    for d in started:
        d.close()


@pytest.fixture(scope="module")
def shared_daemon(tmp_path_factory):
    """One daemon for a module of tests that only talk to it."""
    d = DaemonProcess(tmp_path_factory.mktemp("shared"), daemon_config())
    yield d
    d.close()


@pytest.fixture
def board(tmp_path):
    """A fingertip board in software (sim.board) streaming tecdar-imu/1 on a pseudo-terminal, as a
    real arm's daemon reads it (`imu.source: serial`, `imu.serial.port: str(board.link)`)."""
    from tecdard.sim.board import Board, PtyDevice, StreamThread
    device = PtyDevice(tmp_path / "ttyIMU")
    streamer = StreamThread(device, Board()).start()
    yield device
    streamer.join()
    device.close()


def rotate_on_the_cutter(d, angle_deg: float = 20.0) -> float:
    """A `rotate` of angle_deg on the simulated paper cutter: it finishes, the handle turns within 2 degrees of
    it, and no fault was raised on the way. Returns the hinge found's distance to the true axis, m."""
    deadline = time.monotonic() + 10.0
    while d.client.command("status")["state"]["faults"] and time.monotonic() < deadline:
        time.sleep(0.1)                  # a board that comes up late: its imu_stale clears first
    reply = d.client.command("rotate", {"angle_deg": angle_deg})
    assert reply["ok"] is True, reply
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 90.0)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-2000:]}"
    sim = ev["result"]["sim"]
    assert abs(sim["angle_deg"] - angle_deg) < 2.0
    # on the way: a fault of the daemon's start (a board that came up late on a loaded machine, imu_stale that then
    # cleared) is not the rotate's (CI 2026-12-07: sim-firmware's host board 1 s late)
    started = next(e["t"] for e in d.client.event_log if e["kind"] == "task_started" and e.get("task") == reply["task"])
    faults = [e for e in d.client.event_log if e["kind"] == "fault" and e["t"] >= started]
    assert not faults, f"{faults}\n{d.log()[-2000:]}"
    return distance_to_axis(np.array(ev["result"]["hinge"]["p"]), np.array(sim["hinge_point"]),
                            np.array(sim["hinge_axis"]))
