"""`tecdard export --lerobot` (issue 52): a dataset's size and the export's time per episode-minute; writes
benchmarks/lerobot_export.md.

    python -m benchmarks.lerobot_export

- built episodes of 1 and 5 minutes (tests/test_lerobot_export.py's daemon_recording: a board at 6667 Hz whose
  samples are noise, the worst case for compression; an arm at 500 Hz; ticks at 50 Hz), one per dataset;
- the simulated daemon's own recording of one rotate (record.enabled), scaled to a minute.
Time is the command's wall time (its Python start included), on this machine's 2 cores; size is the dataset
directory's. Nothing here is a real rig's recording.
"""
from __future__ import annotations

import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.conftest import DaemonProcess, daemon_config, tecdard  # noqa: E402
from tests.test_lerobot_export import daemon_recording  # noqa: E402

OUT = ROOT / "benchmarks" / "lerobot_export.md"


def measure(recording: pathlib.Path, work: pathlib.Path) -> dict:
    out = work / f"ds-{recording.stem}"
    t0 = time.monotonic()
    res = tecdard("export", "--lerobot", str(out), str(recording))
    seconds = time.monotonic() - t0
    if res.returncode != 0:
        raise SystemExit(res.stderr)
    import json
    info = json.loads((out / "meta" / "info.json").read_text())
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    minutes = info["total_frames"] / info["fps"] / 60.0
    return {"name": recording.name, "minutes": minutes, "frames": info["total_frames"],
            "npz_mb": recording.stat().st_size / 1e6, "mb": size / 1e6, "s": seconds}


def daemon_episode(work: pathlib.Path) -> pathlib.Path:
    (work / "daemon").mkdir()
    d = DaemonProcess(work / "daemon", daemon_config(**{"record.enabled": True}))
    try:
        reply = d.client.command("rotate", {"angle_deg": 30.0})
        d.client.wait_event(("task_done", "task_failed"), reply["task"], 90.0)
        written = d.client.wait_event(("recording_written",), None, 15.0)
    finally:
        d.close()
    return pathlib.Path(written["path"])


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        for minutes in (1, 5):
            path = work / f"built-{minutes}min.npz"
            daemon_recording(path, seconds=60.0 * minutes)
            rows.append(measure(path, work))
        rows.append(measure(daemon_episode(work), work))
    lines = ["# `tecdard export --lerobot`: size and time per episode-minute", "",
             "`python -m benchmarks.lerobot_export`, on this machine's 2 cores. One episode per dataset; time is the "
             "command's wall time, its Python start (about 1 s) included. The built episodes' IMU is noise (the "
             "worst case for compression); the daemon's is the simulator's rotate. Nothing here is a real rig's.", "",
             "| episode | minutes | frames | recording (MB) | dataset (MB) | MB per minute | export (s) | s per minute |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['name']} | {r['minutes']:.2f} | {r['frames']} | {r['npz_mb']:.1f} | {r['mb']:.1f} | "
                     f"{r['mb'] / r['minutes']:.1f} | {r['s']:.2f} | {r['s'] / r['minutes']:.2f} |")
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
