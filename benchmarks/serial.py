"""Serial driver benchmark (issue 5): parser throughput and the CPU cost of a 6667 samples/s pty stream."""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.sim.board import Board, BoardParams  # noqa: E402
from tecdard.drivers.imu_wire import WireParser  # noqa: E402
from tecdard.drivers.serial_imu import SerialImuSource, SerialParams  # noqa: E402

WRITER = """
import sys, time
sys.path.insert(0, {root!r})
from tecdard.sim.board import Board, BoardParams, PtyDevice, StreamThread
dev = PtyDevice({link!r})
st = StreamThread(dev, Board(BoardParams(samples_per_packet={n}))).start()
print("ready", flush=True)
time.sleep({seconds} + 2)
st.join(); dev.close()
"""


def parser_throughput(seconds: float = 10.0, n: int = 8) -> dict:
    board = Board(BoardParams(samples_per_packet=n))
    k = int(6667 * seconds)
    rng = np.random.default_rng(0)
    data = b"".join(board.packets(rng.normal(0, 0.1, (k, 3)), rng.normal(0, 1, (k, 3))))
    src = SerialImuSource(SerialParams(port="unused"))
    t0 = time.process_time()
    for i in range(0, len(data), 4096):
        src.decode(data[i:i + 4096], 1.0 + i / 84000.0)
    el = time.process_time() - t0
    p = WireParser()
    t1 = time.process_time()
    for i in range(0, len(data), 4096):
        p.feed(data[i:i + 4096])
    el_p = time.process_time() - t1
    return {"bytes": len(data), "seconds": seconds, "decode_x": seconds / el, "parse_x": seconds / el_p,
            "samples": src.parser.counters.samples}


def pty_cpu(seconds: float = 10.0, n: int = 8) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        link = os.path.join(tmp, "ttyIMU")
        w = subprocess.Popen([sys.executable, "-c", WRITER.format(root=str(ROOT), link=link, n=n, seconds=seconds)],
                             stdout=subprocess.PIPE, text=True)
        assert w.stdout.readline().strip() == "ready"
        src = SerialImuSource(SerialParams(port=link))
        src.open()
        samples = 0
        c0, t0 = time.process_time(), time.monotonic()
        while time.monotonic() - t0 < seconds:
            out = src.read(0.05)
            if out is not None:
                samples += len(out[0])
        cpu, wall = time.process_time() - c0, time.monotonic() - t0
        src.close()
        w.wait(30)
    return {"n": n, "samples_per_s": samples / wall, "cpu_pct": 100 * cpu / wall, "counters": src.counters()}


def main() -> int:
    lines = ["# Serial driver benchmark", ""]
    for n in (8, 32):
        pt = parser_throughput(n=n)
        lines.append(f"- parse only, {n} samples/packet: {pt['parse_x']:.0f}x real time; parse + scale + "
                     f"timestamp: {pt['decode_x']:.0f}x real time (target >= 20x)")
    for n in (8, 32):
        r = pty_cpu(n=n)
        lines.append(f"- pty stream, {n} samples/packet: {r['samples_per_s']:.0f} samples/s sustained, reader CPU "
                     f"{r['cpu_pct']:.1f} % of one core (target < 15 %), crc errors {r['counters']['crc_errors']}, "
                     f"samples lost {r['counters']['samples_lost']}")
    out = ROOT / "benchmarks" / "serial.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
