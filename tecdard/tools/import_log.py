"""`tecdard import SRC OUT.npz`: a lab's own log as a tecdar-recording/1 file (tecdard/recording/imports.py).

SRC is a rosbag2 directory, a ROS 1 bag or an MCAP file (sensor_msgs/Imu, with sensor_msgs/JointState
or /tf), or with --csv a YAML map of CSV files. The mount and clock offset are the config's
(imu.imu_in_tcp_quat, imu.time_offset_s, as `tecdard calibrate-mount` prints them) or --mount and
--time-offset-s; the arm for joint states is the config's robot section or --model.
"""
from __future__ import annotations

import sys

from tecdard.safejson import show


def add_parser(sub) -> None:
    p = sub.add_parser("import", help="a rosbag2, MCAP or CSV log as a tecdar recording (localize, plot and "
                                      "calibrate-eta then run on it)", description=__doc__.split("\n\n")[0])
    p.add_argument("source", help="a rosbag2 directory, a .bag, a .mcap file; with --csv, the YAML map")
    p.add_argument("out", help="OUT.npz")
    p.add_argument("--csv", action="store_true", help="SOURCE is a YAML map of CSV files (docs/recordings.md)")
    p.add_argument("--imu-topic", help="the sensor_msgs/Imu topic (default: the only one)")
    p.add_argument("--joints-topic", help="the sensor_msgs/JointState topic (default: the only one)")
    p.add_argument("--tf", metavar="BASE:TOOL", help="the TCP's pose from /tf and /tf_static, TOOL's frame in BASE's, "
                                                     "instead of the joint states")
    p.add_argument("--config", help="a daemon config: its imu mount and time offset, and its robot for joint states")
    p.add_argument("--model", help="the arm for joint states instead of the config's (panda, ur5, ur10, ...)")
    p.add_argument("--mount", metavar="X,Y,Z,W", help="the IMU's mount, TCP <- IMU, instead of the config's")
    p.add_argument("--time-offset-s", type=float, help="the IMU's stamps less the arm's, s, instead of the config's")
    p.set_defaults(func=main)


def _arm_and_calibration(args):
    """(the arm's model or None, the mount quaternion, the time offset s) from --config and the flags."""
    import numpy as np

    from tecdard.config import Config
    from tecdard.options import read_options
    from tecdard.robots.model import ArmModel
    from tecdard.runtime.rig_options import ImuOptions, RobotOptions
    model, mount, offset = None, (0.0, 0.0, 0.0, 1.0), 0.0
    if args.config:
        cfg = Config.load(args.config)
        imu = read_options(ImuOptions, cfg.section("imu"))
        mount, offset = tuple(imu.imu_in_tcp_quat), imu.time_offset_s
        own = read_options(RobotOptions, cfg.section("robot"))
        if not args.tf:
            model = ArmModel(own.model if own.urdf is None else "urdf", list(own.tool_offset), list(own.tool_quat),
                             urdf=own.urdf, tcp_link=own.tcp_link)
    if args.model:
        model = ArmModel(args.model)
    if args.mount:
        try:
            mount = tuple(float(x) for x in args.mount.split(","))
        except ValueError:
            mount = ()
        if len(mount) != 4 or not np.all(np.isfinite(mount)) or abs(np.linalg.norm(mount) - 1.0) > 1e-3:
            raise ValueError(f"--mount: expected a unit quaternion x,y,z,w, got {show(args.mount)}")
    if args.time_offset_s is not None:
        if not -0.5 <= args.time_offset_s <= 0.5:
            raise ValueError(f"--time-offset-s: expected -0.5..0.5 s, got {args.time_offset_s:g}")
        offset = args.time_offset_s
    return model, mount, offset


def main(args) -> int:
    """`tecdard import`: exit 0 with one line of what was written, 2 with one line of what was wrong."""
    from tecdard.config import ConfigError
    from tecdard.recording.format import RecordingError, load_recording, save_recording
    from tecdard.recording.imports import ImportFailure, read_bag, to_recording
    from tecdard.recording.imports_csv import read_csv
    from tecdard.robots.model import UnknownRobotError

    def bad(msg: str) -> int:
        print(f"tecdard import: {msg}", file=sys.stderr)
        return 2

    tf = None
    if args.tf:
        base, _, tool = args.tf.partition(":")
        if not base or not tool:
            return bad(f"--tf: expected BASE:TOOL frame ids, got {show(args.tf)}")
        tf = (base.lstrip("/"), tool.lstrip("/"))
    try:
        model, mount, offset = _arm_and_calibration(args)
        if args.csv:
            streams = read_csv(args.source)
        else:
            try:
                streams = read_bag(args.source, args.imu_topic, args.joints_topic, tf)
            except ImportError as exc:
                return bad(f"reading bags needs rosbags and mcap ({exc.name}): pip install 'tecdar[ros2,viz]'")
        rec = to_recording(streams, mount, offset, model)
        save_recording(args.out, rec)
        rec = load_recording(args.out)                # what localize will read: checked as it will be
    except (ImportFailure, ConfigError, UnknownRobotError, RecordingError, ValueError) as exc:
        return bad(str(exc).splitlines()[0][:300])
    except OSError as exc:
        return bad(f"{show(args.out, 200)}: {exc.strerror or exc}")
    print(f"wrote {args.out}: {len(rec.imu_t)} IMU samples at {rec.imu_rate_hz:.4g} Hz, {len(rec.tcp_t)} TCP poses at "
          f"{rec.tcp_rate_hz:.4g} Hz over {rec.duration_s:.2f} s, mount {[round(float(x), 4) for x in rec.imu_in_tcp_quat]}"
          f", IMU stamps less {offset * 1e3:g} ms")
    return 0
