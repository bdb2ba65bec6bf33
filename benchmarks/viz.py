"""What the live Foxglove view and live recording cost the daemon (issue 20); writes benchmarks/viz.md.

    python -m benchmarks.viz [--seconds S]

The daemon on the simulated robot, idle (the IMU streaming at 6.7 kHz, proprioception at 65 Hz),
its process's CPU (the simulator's child excluded) over S seconds, in three runs:
- as configs/sim.yaml has it (`record.enabled` false: the recorder still keeps its pre-onset
  buffer, for `record start`);
- with `record.enabled` (the same, and an onset would open a capture);
- with the live view on and a WebSocket client subscribed to every channel (all four published).
The machine is shared: the figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import platform
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.ur import cpu_s  # noqa: E402
from tecdard.tools.demo import free_port  # noqa: E402
from tests.conftest import DaemonProcess, daemon_config  # noqa: E402

SETTLE_S = 2.0


def idle_cpu(overrides: dict, seconds: float, subscribe_port: int | None = None) -> float:
    """The daemon process's CPU, as a share of one core, idle for `seconds`."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        d = DaemonProcess(pathlib.Path(tmp), daemon_config(**overrides))
        stack.callback(d.close)
        ws = None
        if subscribe_port is not None:
            from websockets.sync.client import connect
            ws = stack.enter_context(connect(f"ws://127.0.0.1:{subscribe_port}",
                                             subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]))
            channels = {}
            while len(channels) < 4:
                msg = json.loads(ws.recv(timeout=5.0))
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c["id"] for c in msg["channels"]})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": k, "channelId": c} for k, c in enumerate(channels.values(), start=1)]}))
        time.sleep(SETTLE_S)
        c0, t0 = cpu_s(d.proc.pid), time.monotonic()
        received = 0
        while time.monotonic() - t0 < seconds:
            if ws is not None:
                try:
                    ws.recv(timeout=0.1)
                    received += 1
                except TimeoutError:
                    pass
            else:
                time.sleep(0.1)
        share = (cpu_s(d.proc.pid) - c0) / (time.monotonic() - t0)
        if ws is not None and received == 0:
            raise RuntimeError("the live view sent nothing")
        return share


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    port = free_port()
    plain = idle_cpu({}, args.seconds)
    recording = idle_cpu({"record.enabled": True}, args.seconds)
    view = idle_cpu({"viz.foxglove": {"enabled": True, "port": port}}, args.seconds, subscribe_port=port)
    lines = [
        f"# Live recording and the live Foxglove view: their cost ({time.strftime('%Y-%m-%d')}, "
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()})", "",
        "`python -m benchmarks.viz`: the daemon on the simulated robot, idle (IMU at 6.7 kHz, "
        f"proprioception at 65 Hz), its own process's CPU over {args.seconds:g} s (the simulator's child "
        "excluded). The machine is shared; nothing here is a test.", "",
        "| daemon | CPU, share of one core |", "|---|---|",
        f"| as configs/sim.yaml: `record.enabled` false (the recorder keeps its pre-onset buffer for "
        f"`record start`) | {100 * plain:.1f} % |",
        f"| `record.enabled` | {100 * recording:.1f} % |",
        f"| live view on, a client subscribed to `/imu`, `/tf`, `/contact`, `/events` | {100 * view:.1f} % |", "",
    ]
    text = "\n".join(lines)
    (ROOT / "benchmarks" / "viz.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
