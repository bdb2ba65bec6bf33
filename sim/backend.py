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

import numpy as np

from tecdard.drivers.serial_imu import SerialParams
from tecdard.robots.backends import BackendContext
from tecdard.sim.board import BoardParams
from tecdard.sim.imu import SimImuParams
from tecdard.sim.process import SimProcess, SimSpec
from tecdard.sim.robot import SimRobotParams
from tecdard.sim.world import HingeParams, PivotParams

PTY_DIR_PREFIX = "tecdar-imu-"  # sim-wire: <tmp>/tecdar-imu-<pid>-<random>/ttyIMU


def remove_stale_pty_dirs() -> None:
    """sim-wire pty directories of daemons that no longer run (killed, so they could not clean up)."""
    for path in pathlib.Path(tempfile.gettempdir()).glob(PTY_DIR_PREFIX + "*"):
        pid = path.name[len(PTY_DIR_PREFIX):].split("-")[0]
        if pid.isdigit() and int(pid) != os.getpid() and not pathlib.Path(f"/proc/{pid}").exists():
            shutil.rmtree(path, ignore_errors=True)


class SimBackend:
    """The robot (a SimProcess: receive and control as any backend), and with `imu.source: sim` the
    IMU source too; with `sim-wire` the serial parameters of the board's pseudo-terminal."""

    def __init__(self, ctx: BackendContext):
        from tecdard.config import ConfigError
        sim = ctx.cfg.section("sim")
        sim_imu = sim.section("imu")
        imu_params = SimImuParams.from_config(sim_imu, default_mount=ctx.imu_mount)
        robot_params = SimRobotParams.from_config(sim.section("robot"), ctx.q_home)
        hinge = HingeParams.from_config(sim.section("hinge")) if sim.has("hinge") else None
        try:
            pivot = PivotParams.from_config(sim.section("pivot")) if sim.has("pivot") else None
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if hinge is not None and pivot is not None:
            raise ConfigError("sim.pivot: give one world, sim.hinge or sim.pivot, not both")
        model = ctx.model
        self.spec = SimSpec(arm=model.name, tool_offset=list(model.tool_offset), tool_quat=list(model.tool_quat),
                            robot=robot_params, imu=imu_params, seed=sim.getint("seed", 0, minval=0),
                            hinge=hinge, pivot=pivot,
                            imu_out={"sim": "pipe", "sim-wire": "wire", "serial": "none"}[ctx.imu_source])
        # the data rate of the simulated source: the chip's, or the board's (whole hertz on the wire)
        self.imu_odr_hz = float(int(round(imu_params.odr_hz))) if ctx.imu_source == "sim-wire" else imu_params.odr_hz
        self.serial_params: SerialParams | None = None
        self.pty_dir: str | None = None
        if ctx.imu_source == "sim-wire":
            # made at start, removed at exit; one left by a killed daemon is removed by the next
            self.pty_dir = os.path.join(tempfile.gettempdir(), f"{PTY_DIR_PREFIX}{os.getpid()}-{secrets.token_hex(4)}")
            self.spec.pty_link = os.path.join(self.pty_dir, "ttyIMU")
            self.spec.board = BoardParams(odr_hz=int(round(imu_params.odr_hz)), gyro_fs_dps=imu_params.gyro_fs_dps,
                                          accel_fs_g=imu_params.accel_fs_g)
            self.serial_params = SerialParams(port=self.spec.pty_link, odr_hz=self.spec.board.odr_hz,
                                              gyro_fs_dps=self.spec.board.gyro_fs_dps,
                                              accel_fs_g=self.spec.board.accel_fs_g)
        factory = self.spec.world_factory()
        if factory is not None:
            # the world is built once here, at the home pose, so a bad one never half-starts the daemon
            oMtcp = model.fk(ctx.q_home)
            try:
                factory(oMtcp.translation, oMtcp.rotation)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        # The simulated arm, world and IMU run in a process of their own, as a real arm and board do
        # (sim/process.py): the daemon's threads never starve them of the GIL.
        self.robot = SimProcess(self.spec, model.nq)
        self.imu = self.robot if ctx.imu_source == "sim" else None

    def start(self) -> None:
        if self.pty_dir is not None:
            remove_stale_pty_dirs()
            os.makedirs(self.pty_dir, mode=0o700)
        self.robot.start()

    def close(self) -> None:
        self.robot.stop()
        if self.pty_dir is not None:
            shutil.rmtree(self.pty_dir, ignore_errors=True)
            self.pty_dir = None

    def annotate(self, event: dict) -> dict:
        """A task's end event with the simulated world's truth (docs/zenoh-api.md, `sim`)."""
        return with_truth(event, self.robot.truth())


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


def build(ctx: BackendContext) -> SimBackend:
    return SimBackend(ctx)
