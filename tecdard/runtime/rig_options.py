"""The `robot` and `imu` sections' own options, as the daemon reads them: which arm, its tool and home, and
how the fingertip's samples are held and mounted. A backend reads its own subsection (robot.ur, robot.franka,
robot.ros2), the board its own (imu.serial)."""
from __future__ import annotations

from dataclasses import dataclass

from tecdard.options import option
from tecdard.robots import backends

MAX_ROBOT_NAME_CHARS = 64      # the name is a chunk of every key expression
MAX_TOOL_OFFSET_M = 0.5        # flange -> TCP; anything longer is a typo (mm for m), not a tool


@dataclass(frozen=True)
class RobotOptions:
    """The `robot` section's own options."""
    name: str = option("sim", "the robot's name: a chunk of every key (tecdar/NAME/...), ASCII letters, digits, "
                              "'-' or '_'", max_len=MAX_ROBOT_NAME_CHARS)
    backend: str = option("sim", "what drives the arm: sim, ur (ur-rtde), franka (franky), ros2 (observe an arm "
                                 "that ROS 2 drives)", choices=tuple(backends.names()))
    model: str = option("panda", "the arm (robots.model's: panda, fr3, ur3 ... ur16e)", max_len=64)
    urdf: str | None = option(None, "instead of model: the user's URDF", kind="optstr", max_len=4096)
    tcp_link: str | None = option(None, "with urdf: the link the TCP (tool_offset, tool_quat) is offset from",
                                  kind="optstr", max_len=200)
    tool_offset: tuple = option((0.0, 0.0, 0.0), "flange -> TCP, in the flange frame", unit="m", kind="vec3")
    tool_quat: tuple = option((0.0, 0.0, 0.0, 1.0), "flange -> TCP rotation, (x, y, z, w)", kind="quat")
    q_home: list | None = option(None, "the home posture (`home` goes there; inside the workspace box); required "
                                       "unless the backend only observes the arm", unit="rad", kind="custom",
                                 shown="required (observed arm: the model's ready pose)")


@dataclass(frozen=True)
class ImuOptions:
    """The `imu` section's own options (the board's are imu.serial's)."""
    source: str = option("", "where the fingertip's samples come from: serial (the board, docs/imu-serial.md), or "
                             "the simulator's sim | sim-wire | sim-firmware; the backend names those it reads",
                         kind="custom", shown="the backend's first: sim (simulator), serial (an arm)")
    ring_capacity: int = option(65536, "IMU samples the ring holds between the acquisition and the estimator",
                                minval=1024, maxval=1 << 22)
    imu_in_tcp_quat: tuple = option((0.0, 0.0, 0.0, 1.0), "the IMU's mount, (x, y, z, w), TCP <- IMU, as calibrated",
                                    kind="quat")
    time_offset_s: float = option(0.0, "the IMU's stamps less the arm's states' for the same instant, as "
                                       "calibrated (tecdard calibrate-mount): taken off every IMU stamp",
                                  unit="s", minval=-0.5, maxval=0.5)
