"""`robot.backend: sim`: the simulated arm, its world and its fingertip IMU in a child process.

Reads the config's `sim` section. With `imu.source: sim` the child's IMU samples reach the daemon
through a pipe; with `sim-wire` the child's board speaks tecdar-imu/1 on a pseudo-terminal that the
daemon's real serial driver reads (parser, scaling and clock sync all run in simulation); with
`serial` a real board is read and the simulated one is silent.
"""
from __future__ import annotations

import math
import os
import pathlib
import secrets
import shutil
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from tecdard.drivers.serial_imu import SerialImuSource, SerialParams
from tecdard.host import Check
from tecdard.options import option, read_options
from tecdard.robots.backend import JointState, Recovery, RobotBackend
from tecdard.robots.backends import BackendContext
from tecdard.shipped import host_board
from tecdard.sim.board import BoardParams
from tecdard.sim.imu import SimImuParams
from tecdard.sim.rig import RigParams
from tecdard.sim.process import SimProcess, SimSpec
from tecdard.sim.robot import SimRobotParams
from tecdard.sim.world import HingeParams, PivotParams

PTY_DIR_PREFIX = "tecdar-imu-"  # sim-wire: <tmp>/tecdar-imu-<pid>-<random>/ttyIMU


@dataclass(frozen=True)
class SimOptions:
    """The `sim` section's own options (its arm, IMU and world are sim.robot's, sim.imu's and sim.hinge's or
    sim.pivot's)."""
    seed: int = option(0, "the simulation's random seed (noise, biases)", minval=0)
    host_board: str = option("", "sim-firmware: the firmware's host board executable; \"\": the one shipped (a "
                                 "wheel's), or a checkout's `make firmware` build", max_len=4096)


def remove_stale_pty_dirs() -> None:
    """sim-wire pty directories of daemons that no longer run (killed, so they could not clean up)."""
    for path in pathlib.Path(tempfile.gettempdir()).glob(PTY_DIR_PREFIX + "*"):
        pid = path.name[len(PTY_DIR_PREFIX):].split("-")[0]
        if pid.isdigit() and int(pid) != os.getpid() and not pathlib.Path(f"/proc/{pid}").exists():
            shutil.rmtree(path, ignore_errors=True)


class SimBackend(RobotBackend):
    name = "sim"
    recoverable = frozenset({"robot_protective_stop"})

    """The simulated arm (a SimProcess child) as a robot backend, and the simulator's own IMU sources:
    `sim` (samples on a pipe) and `sim-wire` (tecdar-imu/1 on a pty, the real serial driver reading it)."""

    # The simulated controller publishes at sim.robot.proprio_rate_hz (65 Hz, 15 ms) and hands its
    # states over once a physics slice (10 ms), in a process that shares the host with the daemon
    # (on a loaded 2-core machine it was seen 50-60 ms behind): twice a real arm's budget.
    STATE_AGE_S = 0.1
    imu_sources = ("sim", "sim-wire", "sim-firmware", "serial")

    def __init__(self, ctx: BackendContext):
        sim = ctx.cfg.section("sim")
        own = read_options(SimOptions, sim)
        sim_imu = sim.section("imu")
        self.imu_params = SimImuParams.from_config(sim_imu, default_mount=ctx.imu_mount)
        robot_params = SimRobotParams.from_config(sim.section("robot"), ctx.q_home)
        hinge = HingeParams.from_config(sim.section("hinge")) if sim.has("hinge") else None
        pivot = PivotParams.from_config(sim.section("pivot")) if sim.has("pivot") else None
        if hinge is not None and pivot is not None:
            raise sim.error("pivot", "give one world, sim.hinge or sim.pivot, not both")
        model = ctx.model
        self.spec = SimSpec(arm=model.name, tool_offset=list(model.tool_offset), tool_quat=list(model.tool_quat),
                            robot=robot_params, imu=self.imu_params, seed=own.seed,
                            hinge=hinge, pivot=pivot, imu_out="pipe",
                            rig=RigParams.from_config(sim.section("rig")) if sim.has("rig") else None)
        self.pty_dir: str | None = None
        self.host_board = own.host_board or str(host_board())
        factory = self.spec.world_factory()
        if factory is not None:
            # the world is built once here, at the home pose, so a bad one never half-starts the daemon
            oMtcp = model.fk(ctx.q_home)
            try:
                factory(oMtcp.translation, oMtcp.rotation)
            except ValueError as exc:        # "hinge.point: ...": the world's key under `sim`
                key, _, problem = str(exc).partition(": ")
                raise sim.error(key, problem) from None
        # The simulated arm, world and IMU run in a process of their own, as a real arm and board do
        # (sim/process.py): the daemon's threads never starve them of the GIL.
        self.process = SimProcess(self.spec, model.nq)
        self._check_states(ctx, "simulated arm")
        self.process.gate = self.state_check

    def imu_source(self, kind: str, section):
        """sim: the child's samples on their pipe; sim-wire: the child's board on a pty, read by the
        serial driver; serial: a real board (the simulated one silent)."""
        if kind == "sim":
            self.spec.imu_out = "pipe"
            return self.process.imu
        if kind == "sim-wire":
            return SimWireSource(self._wire())
        if kind == "sim-firmware":
            if not os.access(self.host_board, os.X_OK):
                raise section.error("source", f"sim-firmware runs the firmware's host board, and {self.host_board} "
                                              "is not there (build it with `make firmware`, or set sim.host_board)")
            params = self._wire()
            params.link = "uart"             # the host board models its UART at 2 Mbaud
            self.spec.imu_out = "firmware"
            self.spec.host_board = self.host_board
            return SimWireSource(params)
        self.spec.imu_out = "none"
        return super().imu_source(kind, section)

    def _wire(self) -> SerialParams:
        """The simulated board on a pty (made at start, removed at exit; one left by a killed daemon is
        removed by the next): its serial parameters."""
        imu = self.imu_params
        self.spec.imu_out = "wire"
        self.pty_dir = os.path.join(tempfile.gettempdir(), f"{PTY_DIR_PREFIX}{os.getpid()}-{secrets.token_hex(4)}")
        self.spec.pty_link = os.path.join(self.pty_dir, "ttyIMU")
        self.spec.board = BoardParams(odr_hz=int(round(imu.odr_hz)), gyro_fs_dps=imu.gyro_fs_dps,
                                      accel_fs_g=imu.accel_fs_g)
        return SerialParams(port=self.spec.pty_link, odr_hz=self.spec.board.odr_hz,
                            gyro_fs_dps=self.spec.board.gyro_fs_dps, accel_fs_g=self.spec.board.accel_fs_g)

    def start(self) -> None:
        if self.pty_dir is not None:
            remove_stale_pty_dirs()
            os.makedirs(self.pty_dir, mode=0o700)
        self.process.start()

    def close(self) -> None:
        self.process.stop()
        if self.pty_dir is not None:
            shutil.rmtree(self.pty_dir, ignore_errors=True)
            self.pty_dir = None

    def read_state(self) -> JointState:
        return self.process.read_state()

    def wait_state(self, seq: int, timeout: float) -> JointState:
        return self.process.wait_state(seq, timeout)

    def feed_states(self, feed) -> bool:
        self.process.on_state = feed
        return True

    def command_joint_velocity(self, qd: np.ndarray) -> None:
        self.process.command_joint_velocity(qd)

    def hold(self) -> None:
        self.process.hold()

    def faults(self) -> dict[str, str]:
        """The simulated controller's protective stop (a force at the TCP beyond sim.robot.protective_stop_force_n),
        held as a real controller holds one, until `recover`."""
        force = self.process.protective_stop
        if force is None:
            return {}
        return {"robot_protective_stop": f"the simulated controller's protective stop: {force:.1f} N at the TCP, "
                                         f"beyond sim.robot.protective_stop_force_n {self.spec.robot.protective_stop_force_n:g} N"}

    def recover(self, timeout_s: float) -> Recovery:
        """Unlock the simulated controller's protective stop, as the dashboard does a UR's."""
        if self.process.protective_stop is None:
            return Recovery(True, ("the arm reports no fault: nothing to recover",))
        deadline = time.monotonic() + timeout_s
        answered, holding = self.process.unlock(timeout_s)
        if not answered:
            return Recovery(False, (), f"the simulation did not answer the unlock within {timeout_s:g} s")
        limit = self.spec.robot.protective_stop_force_n
        if holding is not None:
            return Recovery(False, (), f"the protective stop holds: {holding:.1f} N at the TCP, beyond {limit:g} N; "
                                       "free the tool (a person backdrives the arm or lets go of the object), then "
                                       "`recover` again")
        while self.process.protective_stop is not None and time.monotonic() < deadline:
            time.sleep(0.02)
        return Recovery(True, ("unlocked the simulated controller's protective stop",))

    @property
    def world_control(self) -> "WorldControl | None":
        """`home --reset-world`'s hooks on the simulated world (None without a world)."""
        return WorldControl(self.process) if self.process.spec.world_factory() is not None else None

    def truth(self):
        """The simulated world's truth now (sim.world.SimTruth), or None before the start."""
        return self.process.truth()

    def annotate(self, event: dict) -> dict:
        """A task's end event with the simulated world's truth (docs/zenoh-api.md, `sim`)."""
        return with_truth(event, self.process.truth())


class WorldControl:
    """The simulated world, for a task: let go of the held object, and build a fresh world around the
    gripper (a message each to the simulation process; nothing waits on the control tick)."""

    def __init__(self, process):
        self.process = process

    def let_go(self) -> None:
        self.process.world("let_go")

    def rebuild(self) -> None:
        self.process.world("rebuild")


class SimWireSource(SerialImuSource):
    """`imu.source: sim-wire`: the serial driver on the simulated board's pty."""

    def checks(self) -> list[Check]:
        return [Check("fingertip board", "skip", "imu.source is sim-wire: the simulated board on a pty is read")]


def with_truth(event: dict, truth) -> dict:
    """A task's end event with the simulated world's truth where the task stopped (`sim`: for tests,
    benchmarks and the demo); any other event, or no truth, as it is."""
    if truth is None or event.get("kind") not in ("task_done", "task_failed"):
        return event
    result = event.get("result") or {}
    # the true handle angle, signed about the axis the task rotated about
    axis = (result.get("hinge") or result).get("axis")      # None for a point contact
    axis = truth.hinge_axis if axis is None else np.asarray(axis, float)
    sign = 1.0 if float(np.dot(axis, truth.hinge_axis)) >= 0 else -1.0
    sim = {"hinge_point": truth.hinge_point.tolist(), "hinge_axis": truth.hinge_axis.tolist(),
           "angle_deg": sign * math.degrees(truth.handle_angle_rad),
           "base_displacement": truth.base_displacement_m, **truth.extra}
    if event["kind"] == "task_done":
        return {**event, "result": {**result, "sim": sim}}
    return {**event, "sim": sim}
