"""How soon a client hears of an impact: the onset trigger's latency in the running daemon (issue 37).

    python -m benchmarks.trigger_latency [--rounds N] [--source sim-wire|sim]

The simulated robot brings a block held nearly level down onto a table (the approach of
tests/test_onset_live.py), N times, each followed by a home. For each impact the accelerometer's
trigger fires at a sample (the `contact_onset` event's `detected_t`, on the host's monotonic clock);
a Zenoh client on the same host stamps the event's arrival on the same clock. The difference is what
the trigger, the estimator's batching, the reader, the main thread's publishing and Zenoh add
together. `sim-wire` (default) is the simulated board speaking tecdar-imu/1 on a pseudo-terminal,
read by the daemon's serial driver, as a real board is. Prints a table; nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.conftest import DaemonProcess, daemon_config  # noqa: E402
from tests.test_onset_live import run_rounds  # noqa: E402


def table_scene() -> dict:
    tool_m, tilt = 0.12, np.radians(10.0)
    tip_tcp = [float(tool_m * np.cos(tilt)), 0.0, float(tool_m * np.sin(tilt))]
    return {"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": tip_tcp, "table_height": float(0.487 - tip_tcp[2] - 0.012),
                                            "edge_x": 1.0}}


def measure(rounds: int, source: str) -> np.ndarray:
    """Arrival at the client less the firing sample's time, ms, one per accelerometer onset."""
    import zenoh
    arrivals = []

    def on_event(sample) -> None:
        ev = json.loads(sample.payload.to_string())
        if ev.get("kind") == "contact_onset" and ev.get("trigger") == "accel":
            arrivals.append((time.monotonic() - ev["detected_t"]) * 1e3)

    with tempfile.TemporaryDirectory() as tmp:
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(**{"imu.source": source, **table_scene()}))
        try:
            sub = d.client.session.declare_subscriber(d.client.keys.events,
                                                      zenoh.handlers.Callback(on_event, indirect=False))
            run_rounds(d, [("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                         "stop_angle_deg": 3.0})], rounds)
            sub.undeclare()
        finally:
            d.close()
    return np.array(arrivals)


def measure_board(rounds: int) -> np.ndarray:
    """Knocks on an idle arm's fingertip (no task: the estimator's rest batches), the board on a pty
    sending each 8-sample packet as it is made, as the real board does (sim.board.StreamThread): a
    client's arrival less the time the knock's first packet was written, ms, one per knock."""
    import zenoh
    from tecdard.sim.board import Board, PtyDevice, StreamThread
    from tests.test_onset_live import IMPACT_GAP_S
    arrivals = []

    def on_event(sample) -> None:
        ev = json.loads(sample.payload.to_string())
        if ev.get("kind") == "contact_onset":
            arrivals.append(time.monotonic())

    with tempfile.TemporaryDirectory() as tmp:
        device = PtyDevice(pathlib.Path(tmp) / "ttyIMU")
        board = Board()
        stream = StreamThread(device, board, chunk_s=8 / board.params.odr_hz).start()
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(**{"imu.source": "serial",
                                                               "imu.serial": {"port": str(device.link)}}))
        try:
            sub = d.client.session.declare_subscriber(d.client.keys.events,
                                                      zenoh.handlers.Callback(on_event, indirect=False))
            deadline = time.monotonic() + 20.0
            while d.client.command("status")["state"]["faults"] and time.monotonic() < deadline:
                time.sleep(0.1)
            time.sleep(1.0)
            for _ in range(rounds):
                stream.impact()
                time.sleep(IMPACT_GAP_S)
            sub.undeclare()
        finally:
            d.close()
            stream.join()
            device.close()
    if len(arrivals) != len(stream.written_t):
        raise SystemExit(f"{len(stream.written_t)} knocks gave {len(arrivals)} onsets: no figure")
    return (np.array(arrivals) - np.array(stream.written_t)) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15, help="approaches onto the table, or knocks (default 15)")
    ap.add_argument("--source", default="sim-wire", choices=("sim-wire", "sim", "board"),
                    help="imu.source (default sim-wire); board: knocks on an idle arm, the board's packets "
                         "on a pty as they are made, timed from the knock's first packet")
    args = ap.parse_args()
    if args.source == "board":
        ms = measure_board(args.rounds)
        head = "onset heard by a client after the knock's packet was written"
    else:
        ms = measure(args.rounds, args.source)
        head = "onset heard by a client after its sample"
    print(f"| imu.source | impacts | {head}, ms: p50 / p90 / max |")
    print("|---|---|---|")
    print(f"| {args.source} | {len(ms)} | {np.percentile(ms, 50):.1f} / {np.percentile(ms, 90):.1f} / {ms.max():.1f} |")


if __name__ == "__main__":
    main()
