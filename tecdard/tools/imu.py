"""`tecdard imu --port PATH`: read the fingertip board for a while; rates, counters, status and the latest
sample in SI, to check a board before the daemon runs on it."""
from __future__ import annotations

import json
import sys
import time


def add_parser(sub) -> None:
    p = sub.add_parser("imu", help="read the fingertip IMU board: rates, counters, latest sample")
    p.add_argument("--port", help="serial device path (e.g. /dev/ttyACM0)")
    p.add_argument("--vid-pid", help="find the board by USB VID:PID (hex), e.g. 0403:6014 (an FTDI FT232H bridge)")
    p.add_argument("--serial-number", help="with --vid-pid: the board's USB serial number")
    p.add_argument("--seconds", type=float, default=2.0, help="how long to read (default 2)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=main)


def read_board(src, seconds: float) -> dict:
    """Read an opened SerialImuSource for `seconds`, then close it: its rates, the board's status, its
    counters and the latest sample, in SI (`tecdard imu --json`, `tecdard report`)."""
    t_start = time.monotonic()
    n_samples = 0
    try:
        while time.monotonic() - t_start < seconds:
            out = src.read(0.05)
            if out is not None:
                n_samples += len(out[0])
    finally:
        src.close()
    elapsed = time.monotonic() - t_start
    c = src.counters()
    return {
        "port": src.port_path, "seconds": round(elapsed, 3), "samples": n_samples,
        "sample_rate_hz": round(n_samples / elapsed, 1),
        "byte_rate_bps": round(c["bytes_in"] / elapsed, 1),
        "packet_rate_hz": round(c["good_packets"] / elapsed, 1),
        "part": src.part,
        "status": None if src.status is None else {"odr_hz": src.status.odr_hz, "gyro_fs_dps": src.status.gyro_fs_dps,
                                                   "accel_fs_g": src.status.accel_fs_g, "flags": src.status.flags},
        "counters": c,
        "latest": None if src.latest is None else {"t": src.latest[0], "gyro_rad_s": src.latest[1].tolist(),
                                                   "accel_m_s2": src.latest[2].tolist()},
    }


def main(args) -> int:
    """Read the fingertip board for a while; print rates, counters and the latest sample in SI."""
    from tecdard.drivers.serial_imu import PortError, SerialImuSource, SerialParams

    vid = pid = None
    if args.vid_pid:
        try:
            vid, pid = (int(x, 16) for x in args.vid_pid.split(":"))
        except ValueError:
            print(f"tecdard imu: --vid-pid: expected hex VID:PID such as 0403:6014, got {args.vid_pid!r}",
                  file=sys.stderr)
            return 2
    if not args.port and vid is None:
        print("tecdard imu: give --port PATH or --vid-pid VID:PID", file=sys.stderr)
        return 2
    src = SerialImuSource(SerialParams(port=args.port, vid=vid, pid=pid, serial_number=args.serial_number))
    try:
        src.open()
    except PortError as exc:
        print(f"tecdard imu: {exc}", file=sys.stderr)
        return 1
    report = read_board(src, args.seconds)
    c, elapsed, n_samples = report["counters"], report["seconds"], report["samples"]
    if args.json:
        print(json.dumps(report))
    else:
        st = report["status"]
        print(f"{src.port_path}: {report['sample_rate_hz']:.0f} samples/s, {report['packet_rate_hz']:.0f} packets/s, "
              f"{report['byte_rate_bps'] / 1000:.1f} kB/s over {elapsed:.1f} s")
        print("status: " + ("none received (using config full scales)" if st is None else
                            f"ODR {st['odr_hz']} Hz, gyro {st['gyro_fs_dps']} dps, accel {st['accel_fs_g']} g, flags {st['flags']:#x}"))
        print("sensor: " + (report["part"] or "not said (the board sent no identity packet: firmware older than the LSM6DSO support)"))
        print("counters: " + ", ".join(f"{k} {v}" for k, v in c.items()))
        if report["latest"]:
            g, a = report["latest"]["gyro_rad_s"], report["latest"]["accel_m_s2"]
            print(f"latest: gyro [{', '.join(f'{x:+.4f}' for x in g)}] rad/s, accel [{', '.join(f'{x:+.3f}' for x in a)}] m/s^2")
        else:
            print("latest: no samples received")
    return 0 if n_samples else 1
