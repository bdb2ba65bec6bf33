"""The simulated arm, its world and its fingertip IMU in a process of their own.

A real arm's controller and the fingertip board are devices apart from the daemon: however busy
the daemon is, the arm keeps integrating and the board keeps streaming. The simulation must
behave the same way, or the daemon's stale-IMU stop measures the simulator's stalls. In one
Python process the 1 kHz physics, the 6.7 kHz IMU synthesis, the estimator and the control loop
all take turns on one GIL, and on a busy 2-core machine the physics thread was seen starved for
50-60 ms. So the daemon runs the simulation in a child process (`SimProcess`), which looks to the
daemon like any robot backend (read_state, command_joint_velocity, hold) and, with
`imu.source: sim`, gives an IMU source (PipeImuSource). With `sim-wire` the child writes the board's
`tecdar-imu/1` stream to a pseudo-terminal that the daemon's serial driver reads. The child and the
daemon's handle on it are a robots.child_link child and ChildLink, as the UR and Franka links are.

Links, each a one-way pipe:
- commands, daemon -> child: (t_issued, qd), time-stamped on the shared monotonic clock, so the
  simulated command latency does not include the pipe's;
- state, child -> daemon: every proprioception sample with the world's truth;
- IMU, child -> daemon: sample chunks (t, gyro, accel), one per physics slice, only with
  `imu.source: sim`.
The child stops when the daemon says so or when the daemon's end of the command pipe closes.
"""
from __future__ import annotations

import fcntl
import gc
import logging
import struct
import termios
import threading
import time
from dataclasses import dataclass
from multiprocessing.reduction import ForkingPickler

import numpy as np

from tecdard.drivers.imu_source import ImuSource
from tecdard.drivers.lsm6dsr import Scaling
from tecdard.host import Check
from tecdard.robots.backend import JointState, joint_rates
from tecdard.robots.backends import BackendError
from tecdard.robots.child_link import ChildLink
from tecdard.robots.model import ArmModel
from tecdard.sim.board import Board, BoardParams, FirmwareWire, PtyDevice, PyWire
from tecdard.sim.imu import SimImu, SimImuParams
from tecdard.sim.rig import RigParams
from tecdard.sim.robot import PHYSICS_RATE_HZ, PHYSICS_WAKE_S, SimRobot, SimRobotParams
from tecdard.sim.world import HingeParams, HingeWorld, PivotParams, PivotWorld, SimTruth

log = logging.getLogger("tecdar.sim")

START_TIMEOUT_S = 60.0       # a cold child imports numpy and Pinocchio and loads the URDF
MAX_BEHIND_S = 0.1            # a child this far behind its schedule resumes from now
PIPE_CAPACITY_BYTES = 1 << 20  # asked of the kernel for each child -> daemon pipe (about 2 s of IMU)
MAX_CHUNKS_PER_READ = 64      # the IMU chunks (10 ms each) one read of the pipe takes at most
MESSAGE_HEADER_BYTES = 16     # multiprocessing's length prefix, with room to spare
F_SETPIPE_SZ, F_GETPIPE_SZ = 1031, 1032     # fcntl(2), Linux
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class SimProcessError(BackendError):
    """The simulation process could not start or has gone."""


@dataclass
class SimSpec:
    """Everything the child needs to build the simulation (picklable)."""
    arm: str
    tool_offset: list
    tool_quat: list
    robot: SimRobotParams
    imu: SimImuParams
    seed: int = 0
    hinge: HingeParams | None = None
    pivot: PivotParams | None = None
    imu_out: str = "pipe"            # "pipe": samples to the daemon; "wire": tecdar-imu/1 on a pty from the
                                     # Python board, "firmware": from the firmware's host board; "none"
    pty_link: str | None = None      # with "wire" or "firmware": the board's stable device path
    board: BoardParams | None = None
    rig: RigParams | None = None     # a real rig's disturbances on the IMU (sim.rig; None: none)
    host_board: str | None = None    # with "firmware": the host board's executable
    log_level: int = logging.INFO    # the daemon's, for the child's own log lines

    def world_factory(self):
        if self.hinge is not None:
            return lambda p_tcp, R_tcp: HingeWorld(self.hinge, p_tcp, R_tcp)
        if self.pivot is not None:
            return lambda p_tcp, R_tcp: PivotWorld(self.pivot, p_tcp, R_tcp)
        return None

    def build(self, wire=None, clock=time.monotonic) -> SimRobot:
        """The simulated arm with its world and IMU, not started. Raises ValueError on a world
        that cannot be built (the daemon builds one in its constructor to check the config)."""
        model = ArmModel(self.arm, np.array(self.tool_offset, float), self.tool_quat)
        imu = None if self.imu_out == "none" else SimImu(self.imu, seed=self.seed, wire=wire, rig=self.rig)
        return SimRobot(model, self.robot, self.world_factory(), imu, seed=self.seed, clock=clock)


class PipeSender:
    """Sends pickled messages on a pipe without ever blocking: a message that does not fit in the
    pipe's free space is dropped and counted. The child's one thread must keep real time however
    slowly the daemon reads (or if it has stopped reading)."""

    def __init__(self, conn, capacity: int = PIPE_CAPACITY_BYTES):
        self.conn = conn
        self.dropped = 0
        try:
            fcntl.fcntl(conn.fileno(), F_SETPIPE_SZ, capacity)
        except OSError:
            pass                                  # the system's limit is lower: keep its default
        self.capacity = fcntl.fcntl(conn.fileno(), F_GETPIPE_SZ)

    def send(self, obj) -> bool:
        data = ForkingPickler.dumps(obj)
        unread = struct.unpack("i", fcntl.ioctl(self.conn.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
        if len(data) + MESSAGE_HEADER_BYTES > self.capacity - unread:
            self.dropped += 1
            return False
        self.conn.send_bytes(data)
        return True


def _joined(chunks: list):
    """IMU chunks (t, gyro, accel) as one, or None for none."""
    if not chunks:
        return None
    return chunks[0] if len(chunks) == 1 else tuple(np.concatenate(parts) for parts in zip(*chunks))


def _drain_imu(imu: SimImu):
    """Every IMU chunk synthesised since the last call, as one (t, gyro, accel), or None."""
    chunks = []
    while (chunk := imu.read(0.0)) is not None:
        chunks.append(chunk)
    return _joined(chunks)


def on_grid(t_physics: float) -> float:
    """The child's next wake: half a physics step after the physics' own grid (t_physics, its last
    whole step). Each slice then integrates whole steps to a wake that sleep's jitter (well under
    half a step) never carries across a step: 10 steps, 66-67 IMU samples, every slice. Woken on a
    step's edge instead (a phase set by chance at the child's start), the slices alternated 9 and
    11 steps, 60 and 73 samples, and the estimator, which asks for 66 before an onset, took them
    two at a time: in those runs the onset trigger waited 10 ms longer (issue 37)."""
    return t_physics + 0.5 / PHYSICS_RATE_HZ


def child_main(spec: SimSpec, cmd_conn, state_conn, imu_conn) -> None:
    """The child process: build the simulation, then run it until told to close.

    One thread does everything, slice by slice on an absolute schedule: take the commands that
    have arrived, integrate the physics up to now, send the IMU samples and the proprioception
    samples that the slice made. With the physics, two forwarders and the command reader in
    threads of their own, the child spent much of its CPU handing the GIL between them, and on a
    loaded 2-core machine its physics fell behind real time.
    """
    logging.basicConfig(level=spec.log_level, format=LOG_FORMAT)
    wire = None
    try:
        if spec.imu_out == "wire":
            wire = PyWire(Board(spec.board), PtyDevice(spec.pty_link))
        elif spec.imu_out == "firmware":
            b = spec.board
            wire = FirmwareWire(spec.host_board, spec.pty_link, b.odr_hz, b.gyro_fs_dps, b.accel_fs_g)
        robot = spec.build(wire=wire)
    except Exception as exc:
        state_conn.send(("error", f"{type(exc).__name__}: {exc}"))
        raise
    gc.collect()
    gc.freeze()        # the model and world live as long as the child: no full collection walks them (a stall)
    robot.sync_clock()
    state_conn.send(("ready", robot.read_state(), robot.truth()))
    imu = robot.imu if spec.imu_out == "pipe" else None
    imu_tx, state_tx = PipeSender(imu_conn), PipeSender(state_conn)
    t_next = on_grid(robot.t)
    stopped = None                        # the protective stop as last sent to the daemon
    try:
        while True:
            try:
                while cmd_conn.poll():
                    msg = cmd_conn.recv()
                    if msg[0] == "cmd":
                        robot.command_at(msg[1], msg[2])
                    elif msg[0] == "unlock":
                        state_conn.send(("unlocked", robot.unlock()))
                    elif msg[0] == "world":
                        robot.let_go() if msg[1] == "let_go" else robot.rebuild_world()
                        log.info("sim: the world %s", "is let go" if msg[1] == "let_go" else "is rebuilt at the TCP")
                    elif msg[0] == "close":
                        return
            except (EOFError, OSError):
                log.warning("sim: the daemon has gone; stopping")
                return
            robot.advance_to(time.monotonic())
            try:
                # the slice's proprioception before its IMU samples, so that the daemon's estimator
                # has the states when it takes the samples they cover
                states = robot.drain_states()
                if states:
                    truth = robot.truth()
                    for js in states:
                        state_tx.send(("state", js, truth))
                if robot.protective_stop != stopped:
                    stopped = robot.protective_stop
                    state_tx.send(("protective_stop", stopped))
                if imu is not None and (chunk := _drain_imu(imu)) is not None:
                    imu_tx.send(chunk)
            except (BrokenPipeError, OSError):
                log.warning("sim: the daemon has gone; stopping")
                return
            t_next += PHYSICS_WAKE_S
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                robot.overruns += 1
                if delay < -MAX_BEHIND_S:
                    # said, because the daemon's stale-IMU stop then measures this, not the daemon
                    log.warning("sim: the simulation fell %.0f ms behind real time (the host did not run "
                                "it); resuming from now", -delay * 1e3)
                    t_next = on_grid(robot.t)       # far behind: resume from now, not in a burst
    finally:
        robot.hold()
        if wire is not None:
            wire.close()
        if imu_tx.dropped or state_tx.dropped:
            log.warning("sim: the daemon did not read: %d IMU and %d state messages dropped",
                        imu_tx.dropped, state_tx.dropped)
        _say_losses(robot, wire)


def _say_losses(robot: SimRobot, wire) -> None:
    """At the child's end, one line for what the simulation itself lost on the way, if anything: slices
    it ran late, stops by the arm's own command watchdog, IMU chunks and board frames it dropped."""
    imu = robot.imu
    losses = {"physics slices late": robot.overruns, "command watchdog stops": robot.watchdog_stops,
              "IMU chunks dropped": imu.dropped_chunks if imu is not None else 0,
              "board frames (or firmware samples) dropped": wire.dropped if wire is not None else 0}
    said = ", ".join(f"{n} {what}" for what, n in losses.items() if n)
    if said:
        log.info("sim: %s", said)


class SimProcess(ChildLink):
    """The daemon's handle on the simulation child: receive and command as any robot link, the world's
    truth, and (imu_out "pipe") the IMU chunks on a pipe of their own (PipeImuSource)."""

    error = SimProcessError
    process_name = "tecdar-sim"
    reader_name = "sim-link"
    extra_pipes = 1                   # the IMU chunks
    child = staticmethod(child_main)

    def __init__(self, spec: SimSpec, nq: int):
        super().__init__(spec, START_TIMEOUT_S)
        self.spec = spec
        self.nq = nq
        self._truth: SimTruth | None = None
        self.protective_stop: float | None = None    # the force (N) that stopped the simulated arm, until unlocked
        self.unlock_answered = threading.Event()
        self.unlock_answer: float | None = None
        self.imu = PipeImuSource(self)

    def start(self) -> None:
        """Start the child and wait until it publishes its first state (SimProcessError if it cannot)."""
        self.spec.log_level = logging.getLogger().getEffectiveLevel()
        super().start()

    def _no_answer(self, timeout_s: float) -> str:
        return f"the simulation process did not start within {timeout_s:.0f} s"

    def _ended(self, exitcode) -> str:
        return f"the simulation process exited at start (code {exitcode})"

    def _refused(self, reason: str) -> str:
        return f"the simulation process failed at start: {reason}"

    def _no_state(self) -> str:
        return "the simulation process is not running"

    _not_running = _no_state

    def _ready(self, payload: tuple) -> None:
        state, self._truth = payload
        self._publish(state)

    def _handle(self, msg: tuple) -> None:
        if msg[0] == "state":
            _, state, self._truth = msg
            self._publish(state)
        elif msg[0] == "protective_stop":
            self.protective_stop = msg[1]
        elif msg[0] == "unlocked":             # the answer to `unlock`: None, or the force that still holds it
            self.unlock_answer = msg[1]
            self.unlock_answered.set()

    def _gone(self) -> None:
        proc = self._proc
        if proc is not None and proc.exitcode not in (None, 0):
            log.error("the simulation process exited (code %s)", proc.exitcode)

    @property
    def imu_rx(self):
        """The IMU pipe's reading end, or None before the start."""
        return self._extra_rx[0] if self._extra_rx else None

    def truth(self) -> SimTruth | None:
        return self._truth

    def command_joint_velocity(self, qd: np.ndarray) -> None:
        self._send(("cmd", time.monotonic(), joint_rates(qd, self.nq).copy()))

    def hold(self) -> None:
        self.command_joint_velocity(np.zeros(self.nq))

    def world(self, action: str) -> None:
        """"let_go" of the held object, or "rebuild" a fresh world around the gripper."""
        self._send(("world", action))

    def unlock(self, timeout_s: float) -> tuple[bool, float | None]:
        """Release the simulated controller's protective stop (`recover`): (answered, the force that still holds it
        or None)."""
        self.unlock_answered.clear()
        self._send(("unlock",))
        return self.unlock_answered.wait(timeout_s), self.unlock_answer


class PipeImuSource(ImuSource):
    """`imu.source: sim`: the simulated chip's samples, as the child synthesises them, on their pipe."""

    def __init__(self, link: SimProcess):
        self.link = link

    @property
    def odr_hz(self) -> float:
        """The simulated chip's data rate, Hz."""
        return float(self.link.spec.imu.odr_hz)

    @property
    def part(self) -> str:
        """The chip the simulator models."""
        return "LSM6DSR (simulated)"

    @property
    def saturation(self) -> tuple[float, float]:
        """(gyro rad/s, accel m/s^2) at which the simulated chip clips (its int16 at the full scales)."""
        return Scaling(self.link.spec.imu.gyro_fs_dps, self.link.spec.imu.accel_fs_g).saturation

    def read(self, timeout: float = 0.05):
        """Every chunk waiting, as one (t (n,), gyro (n,3), accel (n,3)), or None after `timeout`
        seconds. All of them: the reader naps between the estimator's batches (up to 20 ms at rest)
        while the child sends a chunk per 10 ms slice, and one chunk a read fell behind until the
        pipe was full and the child dropped samples."""
        conn = self.link.imu_rx
        try:
            if conn is not None and conn.poll(timeout):
                chunks = [conn.recv()]
                while len(chunks) < MAX_CHUNKS_PER_READ and conn.poll(0.0):
                    chunks.append(conn.recv())
                return _joined(chunks)
        except (EOFError, OSError):
            pass
        if conn is None or self.link.exited.is_set():
            time.sleep(timeout)      # the child has gone: no samples, and no busy loop
        return None

    def checks(self) -> list[Check]:
        return [Check("fingertip board", "skip", "imu.source is sim: the simulated fingertip is used")]
