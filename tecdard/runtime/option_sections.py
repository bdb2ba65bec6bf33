"""Every config section the daemon reads and the options class that reads it: `tecdard options` lists them, and the
ROS 2 node's parameters are them (tecdard/ros2/parameters.py). Its imports are made when it is called: each class
lives with what it configures."""
from __future__ import annotations


def sections() -> list[tuple[str, type]]:
    """(path, options class) of every config section, in the order a config lists them."""
    from tecdard.api.commands import Limits
    from tecdard.control import estimators
    from tecdard.control.onset import OnsetOptions
    from tecdard.control.pipeline import PipelineParams
    from tecdard.drivers.serial_imu import SerialParams
    from tecdard.fleet.episodes import StoreParams
    from tecdard.robots.franka_link import FrankaLinkSettings
    from tecdard.robots.gripper import GripperParams
    from tecdard.robots.ros2_observer import ObserverOptions
    from tecdard.robots.state_check import StateOptions
    from tecdard.robots.ur_link import UrLinkSettings
    from tecdard.runtime.control_thread import ControlParams
    from tecdard.runtime.intake import IntakeParams
    from tecdard.runtime.live_view import VizParams
    from tecdard.runtime.network import SecurityOptions, TlsOptions, ZenohOptions
    from tecdard.runtime.recorder import RecordParams
    from tecdard.runtime.rig_options import ImuOptions, RobotOptions
    from tecdard.runtime.ros2_node import Ros2Params
    from tecdard.sim.backend import SimOptions
    from tecdard.sim.imu import SimImuParams
    from tecdard.sim.rig import RigParams
    from tecdard.sim.robot import SimRobotParams
    from tecdard.sim.world import HingeParams, PivotParams
    from tecdard.verbs.map.files import MapSettings
    each_estimator: list[tuple[str, type]] = []
    seen: set[str] = set()
    for spec in estimators.discover().values():
        if spec.section is not None and spec.options is not None and spec.section not in seen:
            seen.add(spec.section)
            each_estimator.append((f"estimator.{spec.section}", spec.options))
    return [("robot", RobotOptions), ("robot", StateOptions), ("robot.ur", UrLinkSettings),
            ("robot.franka", FrankaLinkSettings), ("robot.ros2", ObserverOptions), ("gripper", GripperParams),
            ("zenoh", ZenohOptions), ("zenoh", IntakeParams), ("zenoh", SecurityOptions), ("zenoh.tls", TlsOptions),
            ("ros2", Ros2Params), ("limits", Limits), ("control", ControlParams), ("map", MapSettings),
            ("record", RecordParams), ("store", StoreParams), ("viz.foxglove", VizParams),
            ("imu", ImuOptions), ("imu.serial", SerialParams),
            ("estimator", PipelineParams), ("estimator.onset", OnsetOptions), *each_estimator,
            ("sim", SimOptions), ("sim.robot", SimRobotParams), ("sim.imu", SimImuParams), ("sim.rig", RigParams),
            ("sim.hinge", HingeParams),
            ("sim.pivot", PivotParams)]
