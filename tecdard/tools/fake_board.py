"""`tecdard fake-board`: the simulated fingertip board on a pseudo-terminal, to try the serial path on a
desk without a board. It streams `tecdar-imu/1` (docs/imu-serial.md) as the firmware does: 6667 Hz
samples of a board at rest (gyro noise, gravity on z), eight to a packet, a status packet at start and
every second. `tecdard imu --port PATH` reads it, and so does the daemon with `imu.source: serial`
and `imu.serial.port: PATH`. Ctrl-C ends it (exit 0)."""
from __future__ import annotations

import pathlib
import signal
import sys
import threading


def add_parser(sub) -> None:
    p = sub.add_parser("fake-board", help="run the simulated fingertip board on a pty and print its path",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--link", default=None, metavar="PATH",
                   help="a stable path for the board (a symlink to the pty, as the udev rule makes "
                        "/dev/tecdar-imu); default $XDG_RUNTIME_DIR/tecdar-fake-imu, else /tmp/tecdar-fake-imu")
    p.add_argument("--odr-hz", type=int, default=6667, choices=(1667, 3333, 6667),
                   help="the output data rate the board reports and streams (default %(default)s Hz)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.set_defaults(func=main)


def default_link() -> pathlib.Path:
    import os
    base = os.environ.get("XDG_RUNTIME_DIR") or "/tmp"
    return pathlib.Path(base) / "tecdar-fake-imu"


def main(args) -> int:
    from tecdard.sim.board import Board, BoardParams, PtyDevice, StreamThread
    link = pathlib.Path(args.link) if args.link else default_link()
    if link.exists() and not link.is_symlink():
        print(f"tecdard fake-board: {link} exists and is not a link this tool made; give --link", file=sys.stderr)
        return 2
    try:
        device = PtyDevice(link)
    except OSError as exc:
        print(f"tecdard fake-board: cannot make {link}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    stream = StreamThread(device, Board(BoardParams(odr_hz=args.odr_hz))).start()
    print(f"fake board streaming tecdar-imu/1 at {args.odr_hz} Hz on {link} (Ctrl-C to stop)", flush=True)
    print(f"  try: tecdard imu --port {link} --seconds 3", flush=True)
    print(f"  or in the daemon's config: imu: {{source: serial, serial: {{port: {link}}}}}", flush=True)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        done.wait(args.seconds)
    except KeyboardInterrupt:
        pass
    finally:
        stream.join()
        device.close()
    return 0
