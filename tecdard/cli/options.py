"""`tecdard options [SECTION]`: every config option, with its default, unit, limits and what it does, generated
from the declarations (tecdard.options) that the config reader reads them through; `--markdown` writes
docs/options.md. `tecdard run --help` ends with the same list."""
from __future__ import annotations

import sys

MARKDOWN_HEAD = """# Config options

Every option of a `tecdard run` config, generated from the declarations the daemon reads them through
(`tecdard options --markdown`; tests/test_layout.py holds this page to them). Units are SI unless named;
`limits` are checked at start, and a key nobody declares is an error (a typo never passes silently).
`tecdard options SECTION` prints one section for a terminal. The shipped configs (`configs/sim.yaml`,
`ur5e.yaml`, `fr3.yaml`) set the ones a rig usually changes.
"""


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


def merged() -> list[tuple[str, list[type]]]:
    """The sections with the classes that read each (zenoh's rates and security beside its own)."""
    out: dict[str, list[type]] = {}
    for path, cls in sections():
        out.setdefault(path, []).append(cls)
    return list(out.items())


def markdown() -> str:
    from tecdard.options import cells, rows
    out = [MARKDOWN_HEAD]
    for path, classes in merged():
        out += [f"## `{path}`", "", "| option | default | unit | limits | what it does |", "|---|---|---|---|---|"]
        out += [cells(row) for cls in classes for row in rows(path, cls)]
        out.append("")
    return "\n".join(out)


def text(only: str | None = None) -> str:
    from tecdard.options import text as lines
    return lines(sections(), only)


def main(args) -> int:
    if args.markdown:
        sys.stdout.write(markdown())
        return 0
    known = {path for path, _ in sections()}
    if args.section and not any(p == args.section or p.startswith(args.section + ".") for p in known):
        print(f"tecdard options: no section {args.section!r} (known: {', '.join(sorted(known))})", file=sys.stderr)
        return 2
    print(text(args.section))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("options", help="every config option: default, unit, limits and what it does",
                       description="Every option of the daemon's config, generated from the declarations it is read "
                                   "through (docs/options.md is the same, as tables).")
    p.add_argument("section", nargs="?", help="only this section and those under it (e.g. control, estimator.ekf)")
    p.add_argument("--markdown", action="store_true", help="the tables of docs/options.md")
    p.set_defaults(func=main)
