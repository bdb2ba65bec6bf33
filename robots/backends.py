"""The robot backends, by the name `robot.backend` gives: each a module with `build(BackendContext)` that
returns a robots.backend.RobotBackend. Adding a backend is its module and one line in BACKENDS.

A module is imported only when the config names it, so the daemon never loads a backend it does
not run (the simulator among them).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np

BACKENDS = {                           # robot.backend -> the module whose build() makes it
    "sim": "tecdard.sim.backend",
    "ur": "tecdard.robots.ur",
    "franka": "tecdard.robots.franka",
    "ros2": "tecdard.robots.ros2_observer",
}


class BackendError(RuntimeError):
    """The robot backend could not start, or has gone (the daemon exits 1 with this line)."""


class ModelMismatch(BackendError):
    """The configured arm model does not fit the robot it meets at start (its joints are not the
    robot's): a configuration error, the daemon exits 2 with this line."""


@dataclass(frozen=True)
class BackendContext:
    """What a backend may read when the daemon builds it: the whole config (its own section is
    its to read, with the typed getters), and what the daemon has read already."""
    cfg: object                 # tecdard.config.Config
    model: object               # robots.model.ArmModel, tool offset included
    q_home: np.ndarray          # rad
    imu_mount: list             # imu.imu_in_tcp_quat (x, y, z, w)
    tick_s: float = 0.02        # control.tick_s: how long a joint velocity command holds


def names() -> tuple[str, ...]:
    return tuple(BACKENDS)


def build(name: str, ctx: BackendContext):
    """The backend `name` (a robots.backend.RobotBackend), built from the config (ConfigError on a bad option)."""
    backend = importlib.import_module(BACKENDS[name]).build(ctx)
    backend.name = name
    return backend
