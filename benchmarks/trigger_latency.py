"""How soon a client hears of an impact: the onset trigger's latency in the running daemon (issue 37).

    python -m benchmarks.trigger_latency [--rounds N] [--case NAME ...]

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
import contextlib
import json
import os
import platform
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


@contextlib.contextmanager
def onsets_heard(d):
    """[(a Zenoh client's arrival, monotonic s; the contact_onset event)] as they come, while in the block."""
    import zenoh
    heard = []

    def on_event(sample) -> None:
        ev = json.loads(sample.payload.to_string())
        if ev.get("kind") == "contact_onset":
            heard.append((time.monotonic(), ev))

    sub = d.client.session.declare_subscriber(d.client.keys.events, zenoh.handlers.Callback(on_event, indirect=False))
    try:
        yield heard
    finally:
        sub.undeclare()


def measure(rounds: int, source: str) -> np.ndarray:
    """Arrival at the client less the firing sample's time, ms, one per accelerometer onset."""
    with tempfile.TemporaryDirectory() as tmp:
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(**{"imu.source": source, **table_scene()}))
        try:
            with onsets_heard(d) as heard:
                run_rounds(d, [("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                             "stop_angle_deg": 3.0})], rounds)
        finally:
            d.close()
    return np.array([(at - ev["detected_t"]) * 1e3 for at, ev in heard if ev.get("trigger") == "accel"])


def measure_board(rounds: int, task: bool = False) -> np.ndarray:
    """Knocks on the fingertip, the board on a pty sending each 8-sample packet as it is made, as the real
    board does (sim.board.StreamThread): a client's arrival less the time the knock's first packet was
    written, ms, one per knock. Idle (no task: the estimator's rest batches), or each knock 1 s into an
    `approach` of the simulated arm in free air (2 cm up at 10 mm/s), followed by a `home`."""
    from tecdard.sim.board import Board, PtyDevice, StreamThread
    with tempfile.TemporaryDirectory() as tmp:
        device = PtyDevice(pathlib.Path(tmp) / "ttyIMU")
        board = Board()
        stream = StreamThread(device, board, chunk_s=8 / board.params.odr_hz).start()
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(**{"imu.source": "serial", **table_scene(),
                                                               "imu.serial": {"port": str(device.link)}}))
        try:
            heard = run_knocks(d, stream, rounds, task)
        finally:
            d.close()
            stream.join()
            device.close()
    arrivals = [at for at, _ in heard]
    if len(arrivals) != len(stream.written_t):
        raise SystemExit(f"{len(stream.written_t)} knocks gave {len(arrivals)} onsets: no figure")
    return (np.array(arrivals) - np.array(stream.written_t)) * 1e3


def run_knocks(d, stream, rounds: int, task: bool) -> list:
    """`rounds` knocks on `stream` once the daemon has no fault, idle or each 1 s into an approach (then a
    home): the onsets heard."""
    from tests.test_onset_live import IMPACT_GAP_S, until_idle
    with onsets_heard(d) as heard:
        deadline = time.monotonic() + 20.0
        while d.client.command("status")["state"]["faults"] and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)
        for _ in range(rounds):
            if not task:
                stream.impact()
                time.sleep(IMPACT_GAP_S)
                continue
            until_idle(d.client)
            reply = d.client.command("approach", {"direction": [0.0, 0.0, 1.0], "speed": 0.01, "max_distance": 0.02})
            assert reply["ok"], reply
            time.sleep(1.0)
            stream.impact()
            d.client.wait_event(("task_done", "task_failed"), reply["task"], 30.0)
            reply = d.client.command("home", {"reset_world": True})
            d.client.wait_event(("task_done", "task_failed"), reply["task"], 60.0)
    return heard


CASES = {   # name: (what, how measured, function of rounds)
    "board, idle": ("knocks on an idle arm, the board's packets on a pty as made", "the knock's first packet written",
                    lambda n: measure_board(n)),
    "board, task": ("knocks during an `approach` in free air, the same board", "the knock's first packet written",
                    lambda n: measure_board(n, task=True)),
    "sim-wire, task": ("impacts on the table during an `approach`, the simulator's board on a pty",
                       "the impact's sample", lambda n: measure(n, "sim-wire")),
    "sim-firmware, task": ("the same, the firmware itself as the board (host build)", "the impact's sample",
                           lambda n: measure(n, "sim-firmware")),
    "sim, task": ("the same, the simulator's samples through a pipe", "the impact's sample",
                  lambda n: measure(n, "sim")),
}
OUT = ROOT / "benchmarks" / "trigger_latency.md"


def _row(name: str, ms: np.ndarray) -> str:
    what, since, _ = CASES[name]
    return (f"| {name} | {what} | {since} | {len(ms)} | "
            f"{np.percentile(ms, 50):.1f} / {np.percentile(ms, 90):.1f} / {ms.max():.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15, help="impacts or knocks per case (default 15)")
    ap.add_argument("--case", choices=sorted(CASES), action="append",
                    help="only this case (repeatable); without it every case, written to benchmarks/trigger_latency.md")
    args = ap.parse_args()
    names = args.case or list(CASES)
    head = ["| case | what | from | impacts | onset heard by a Zenoh client, ms: p50 / p90 / max |", "|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    rows = []
    for name in names:
        rows.append(_row(name, CASES[name][2](args.rounds)))
        print(rows[-1], flush=True)
    if not args.case:
        OUT.write_text("\n".join([
            "# The onset trigger's latency, from an impact to a client (issue 53 item 2)", "",
            f"`python -m benchmarks.trigger_latency --rounds {args.rounds}` on {platform.machine()}, "
            f"{os.cpu_count()} cores, Python {platform.python_version()}, {time.strftime('%Y-%m-%d')}; the daemon "
            "and a Zenoh client on the same host, no real-time priority. Simulated boards and arms only: nothing "
            "here ran on hardware. The machine is shared; nothing here is a test.", "",
            *head, *rows, "",
            "The simulator's child makes its samples in 10 ms slices, and each slice reaches the daemon as a "
            "whole: the `sim` cases are timed from the sample, and up to a slice of their figure is the "
            "simulator's. The `board` cases are timed from when the knock's packet reached the port.", ""]))
        print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
