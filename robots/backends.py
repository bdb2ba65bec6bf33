"""The robot backends, by the name `robot.backend` gives: each a robots.backend.RobotBackend class, built
from a BackendContext. Adding a backend is its module and one line in BACKENDS; what it can do (sends
the arm home, only observes it, takes its state from a topic, which IMU sources it reads) it declares
on its class, and the daemon asks that, never its name.

A module is imported only when the config names it, so the daemon never loads a backend it does
not run (the simulator among them).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np

BACKENDS = {                           # robot.backend -> "module:class" of its RobotBackend
    "sim": "tecdard.sim.backend:SimBackend",
    "ur": "tecdard.robots.ur:UrBackend",
    "franka": "tecdard.robots.franka:FrankaBackend",
    "ros2": "tecdard.robots.ros2_observer:Ros2Observer",
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


def declared(name: str) -> type:
    """The class of the backend `name` (robots.backend.RobotBackend): what it can do, before it is built."""
    module, _, cls = BACKENDS[name].partition(":")
    return getattr(importlib.import_module(module), cls)


def build(name: str, ctx: BackendContext):
    """The backend `name` (a robots.backend.RobotBackend), built from the config (ConfigError on a bad option)."""
    backend = declared(name)(ctx)
    backend.name = name
    return backend
