"""`tecdard report`: what a bug report from a rig needs, in one archive (docs/hardware-validation.md).

The archive holds: `versions.json` (tecdard, Python, the OS and every library the daemon runs on), the config
as written (`config.yaml`, its secrets left out), doctor's output (`doctor.txt`), the board's counters
(`board.json`, read for a few seconds where the port is free), the last recordings' names and summaries
(`recordings.json`; not the recordings, which the lab sends as they are), the log's tail (`log-tail.txt`,
from `--log` or the unit's journal) and `README.txt`, which says what each is and what was left out.

Never in it: a file the config names (TLS keys and certificates, the ACL), the environment (the store's
credentials), and any value whose key says password, secret, token, credential, passphrase, private or
base64; a PEM block anywhere is cut out."""
from __future__ import annotations

import contextlib
import datetime
import io
import json
import os
import pathlib
import platform
import re
import shutil
import socket
import subprocess
import sys
import tarfile
import time
from importlib import metadata

LEFT_OUT = "<left out by tecdard report>"
SECRET_KEY = re.compile(r"^(\s*-?\s*[\w.-]*(?:password|secret|token|credential|passphrase|private|base64)[\w.-]*"
                        r"\s*[:=]\s*).+$", re.IGNORECASE | re.MULTILINE)
SECRET_ASSIGN = re.compile(r"((?:password|secret|token|credential|passphrase|private_key|access_key)[\w.-]*"
                           r"\s*[=:]\s*)\S+", re.IGNORECASE)
PEM = re.compile(r"-----BEGIN [A-Z0-9 ]+-----.*?(?:-----END [A-Z0-9 ]+-----|\Z)", re.DOTALL)
PACKAGES = ("tecdard", "numpy", "ruckig", "pin", "example-robot-data", "pyserial", "eclipse-zenoh", "pyyaml",
            "ur-rtde", "franky-control", "mujoco", "foxglove-sdk", "rosbags", "obstore", "duckdb", "numba")


def redact(text: str) -> str:
    """Text with PEM blocks cut out, the values of secret-named keys left out (YAML and key=value)."""
    text = PEM.sub(LEFT_OUT, text)
    text = SECRET_KEY.sub(lambda m: m.group(1) + LEFT_OUT, text)
    return SECRET_ASSIGN.sub(lambda m: m.group(1) + LEFT_OUT, text)


def versions() -> dict:
    out = {"python": sys.version.split()[0], "platform": platform.platform(), "machine": platform.machine(),
           "kernel": platform.release(), "host": socket.gethostname(), "packages": {}}
    for name in PACKAGES:
        with contextlib.suppress(metadata.PackageNotFoundError):
            out["packages"][name] = metadata.version(name)
    return out


def doctor_text(config: str) -> str:
    from tecdard.tools import doctor
    buf = io.StringIO()
    try:
        doctor.main(config, out=buf)
    except Exception as exc:          # a report is made whatever the doctor trips on, and says so
        buf.write(f"doctor stopped: {type(exc).__name__}: {exc}\n")
    return buf.getvalue()


def board_counters(daemon, seconds: float) -> dict:
    """The board read for `seconds` at its configured port: rates and counters, or why not."""
    params = getattr(getattr(daemon, "imu", None), "params", None)
    if daemon is None or params is None or not hasattr(params, "baud"):
        return {"skipped": "imu.source is not serial (or the config is invalid)"}
    if seconds <= 0:
        return {"skipped": "--board-seconds 0"}
    from tecdard.drivers.serial_imu import PortError, SerialImuSource
    src = SerialImuSource(params)
    try:
        src.open()
    except PortError as exc:
        return {"skipped": f"cannot open the board ({exc}); a running daemon holds it: its counters are in "
                           "`tecdard status --json`"}
    from tecdard.tools.imu import read_board
    return read_board(src, seconds)


def recordings(rec_dir: str | None, count: int) -> list[dict]:
    """The newest `count` recordings in rec_dir: name, size, time, and what load_recording finds in them
    (or the line it refuses them with)."""
    from tecdard.recording.format import RecordingError, load_recording
    if not rec_dir or not os.path.isdir(rec_dir):
        return [{"skipped": f"no recordings directory ({rec_dir})"}]
    paths = sorted(pathlib.Path(rec_dir).glob("*.npz"), key=lambda p: p.stat().st_mtime, reverse=True)[:count]
    out = []
    for p in paths:
        row: dict = {"name": p.name, "bytes": p.stat().st_size,
                     "modified_utc": datetime.datetime.fromtimestamp(p.stat().st_mtime, datetime.timezone.utc)
                     .isoformat(timespec="seconds")}
        try:
            rec = load_recording(p)
            row.update(duration_s=round(rec.duration_s, 3), imu_samples=len(rec.imu_t),
                       imu_rate_hz=round(rec.imu_rate_hz, 1), tcp_samples=len(rec.tcp_t),
                       tcp_rate_hz=round(rec.tcp_rate_hz, 1) if len(rec.tcp_t) > 1 else None,
                       grip_force=rec.grip_force is not None,
                       meta=json.loads(redact(json.dumps(rec.meta))) if rec.meta else {})
        except (RecordingError, OSError, ValueError) as exc:
            row["refused"] = str(exc)
        out.append(row)
    return out


def log_tail(log: str | None, lines: int) -> str:
    if log:
        try:
            with open(log, errors="replace") as f:
                return redact("".join(f.readlines()[-lines:]))
        except OSError as exc:
            return f"--log {log}: {exc.strerror or exc}\n"
    if shutil.which("journalctl") is None:
        return "no --log given and no journalctl on this host\n"
    try:
        got = subprocess.run(["journalctl", "-u", "tecdard", "-n", str(lines), "--no-pager", "-o", "short-iso"],
                             capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"journalctl -u tecdard: {exc}\n"
    return redact(got.stdout or got.stderr or "journalctl -u tecdard: nothing\n")


def build(config: str, output: str, log: str | None = None, lines: int = 2000, count: int = 5,
          board_seconds: float = 2.0) -> dict:
    """Write the archive; returns what went into it (name -> bytes)."""
    from tecdard.tools.doctor import load_daemon
    try:
        config_text = redact(pathlib.Path(config).read_text(errors="replace"))
    except OSError as exc:
        config_text = f"{config}: {exc.strerror or exc}\n"
    daemon = None
    if pathlib.Path(config).is_file():
        daemon, _ = load_daemon(config)
    rec_dir = getattr(getattr(daemon, "record_params", None), "dir", None)
    parts = {
        "versions.json": json.dumps(versions(), indent=1),
        "config.yaml": config_text,
        "doctor.txt": doctor_text(config),
        "board.json": json.dumps(board_counters(daemon, board_seconds), indent=1),
        "recordings.json": json.dumps(recordings(rec_dir, count), indent=1),
        "log-tail.txt": log_tail(log, lines),
    }
    parts["README.txt"] = (
        f"tecdard report, {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}, "
        f"config {config}\n\n" + __doc__ + "\n")
    stamp = int(time.time())
    with tarfile.open(output, "w:gz") as tar:
        for name, text in parts.items():
            data = text.encode()
            info = tarfile.TarInfo(f"tecdar-report/{name}")
            info.size, info.mtime, info.mode = len(data), stamp, 0o644
            tar.addfile(info, io.BytesIO(data))
    return {name: len(text.encode()) for name, text in parts.items()}


def main(args) -> int:
    out = args.output or (f"tecdar-report-{socket.gethostname()}-"
                          f"{datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%dT%H%M%SZ')}.tar.gz")
    try:
        made = build(args.config, out, args.log, args.lines, args.recordings, args.board_seconds)
    except OSError as exc:
        print(f"tecdard report: {out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"{out}: " + ", ".join(f"{k} {v} B" for k, v in made.items()))
    print("secrets left out: TLS keys and every file the config names, the environment, secret-named values")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("report", help="bundle what a bug report needs (versions, config, doctor, board, "
                                      "recordings, log) into one archive, secrets left out")
    p.add_argument("--config", default="/etc/tecdar/tecdard.yaml", help="the daemon's config (default: the unit's)")
    p.add_argument("-o", "--output", help="the archive (default tecdar-report-HOST-UTC.tar.gz here)")
    p.add_argument("--log", help="the daemon's log file (default: the tecdard unit's journal)")
    p.add_argument("--lines", type=int, default=2000, help="lines of the log's tail (default 2000)")
    p.add_argument("--recordings", type=int, default=5, help="how many of the newest recordings to summarise "
                                                             "(default 5)")
    p.add_argument("--board-seconds", type=float, default=2.0, help="how long to read the board for its counters; "
                                                                    "unit s; 0: not at all (default 2 s)")
    p.set_defaults(func=main)
