"""`tecdard report` (issue 49): one archive with versions, the config, doctor's output, the board's counters,
the last recordings' summaries and the log's tail; TLS keys and other secrets never in it."""
from __future__ import annotations

import json
import tarfile

import pytest

from tecdard.recording.format import Recording, save_recording
from tecdard.sim.scenarios import Scenario, generate
from tecdard.tools import report
from tests.conftest import ROOT

PEM_BODY = "MIIEvQIBADANBgkqhkiG9w0BAQEFAASCBKcwggSjAgEAAoIBAQC7"


@pytest.mark.slow
def test_a_report_has_what_a_bug_needs_and_no_secret(tmp_path):
    rec_dir = tmp_path / "recordings"
    rec_dir.mkdir()
    fields, _ = generate(Scenario(kind="edge-arc", duration_s=0.6))
    save_recording(rec_dir / "ep-0001.npz", Recording.from_fields(fields))
    (rec_dir / "ep-0002.npz").write_bytes(b"not a recording")
    cfg = (ROOT / "configs" / "sim.yaml").read_text()
    cfg += f"\nrecord:\n  dir: {rec_dir}\n"
    cfg += "# store_password: hunter2-in-a-comment\n"
    config = tmp_path / "tecdard.yaml"
    config.write_text(cfg)
    log = tmp_path / "daemon.log"
    log.write_text("start\nAWS_SECRET_ACCESS_KEY=wJalrXUtnFEMI-K7MDENG\n-----BEGIN PRIVATE KEY-----\n"
                   f"{PEM_BODY}\n-----END PRIVATE KEY-----\nfault imu_stale\n")
    out = tmp_path / "r.tar.gz"
    made = report.build(str(config), str(out), log=str(log), board_seconds=0)
    assert set(made) == {"versions.json", "config.yaml", "doctor.txt", "board.json", "recordings.json",
                         "log-tail.txt", "README.txt"}
    with tarfile.open(out) as tar:
        files = {m.name.split("/", 1)[1]: tar.extractfile(m).read().decode() for m in tar.getmembers()}
    everything = "".join(files.values())
    for secret in ("hunter2", "wJalrXUtnFEMI", PEM_BODY):
        assert secret not in everything, secret
    assert "fault imu_stale" in files["log-tail.txt"]                  # the log itself is kept
    assert "pin" in json.loads(files["versions.json"])["packages"]
    assert "checks:" in files["doctor.txt"] and "config" in files["doctor.txt"]
    assert json.loads(files["board.json"])["skipped"]
    recs = {r["name"]: r for r in json.loads(files["recordings.json"])}
    assert recs["ep-0001.npz"]["imu_rate_hz"] > 1000 and recs["ep-0001.npz"]["duration_s"] > 0.5
    assert "not a NumPy .npz file" in recs["ep-0002.npz"]["refused"]
    assert "record:" in files["config.yaml"]


def test_redact_leaves_out_secret_values_and_keeps_the_rest():
    text = ("tls:\n  key: /etc/tecdar/tls/daemon.key\n  private_key_base64: QUJD\nstore:\n  url: s3://b/p\n"
            "  secret_access_key: abc\n")
    out = report.redact(text)
    assert "QUJD" not in out and "abc" not in out
    assert "/etc/tecdar/tls/daemon.key" in out and "s3://b/p" in out     # a path is not a secret; its file is never read


@pytest.mark.slow
def test_a_report_reads_the_boards_counters_and_doctor_its_stream(tmp_path):
    """The simulated board on a pty (`tecdard fake-board`) as imu.source serial: the report holds its rate and
    counters, and doctor's stream check reads frames from it."""
    import subprocess
    import sys
    link = tmp_path / "fake-imu"
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "fake-board", "--link", str(link), "--seconds", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert proc.stdout.readline().startswith("fake board streaming")
        cfg = (ROOT / "configs" / "sim.yaml").read_text()
        cfg += f"\nimu:\n  source: serial\n  serial:\n    port: {link}\n"
        config = tmp_path / "tecdard.yaml"
        config.write_text(cfg)
        out = tmp_path / "r.tar.gz"
        report.build(str(config), str(out), log=str(config), board_seconds=1.0)
        with tarfile.open(out) as tar:
            files = {m.name.split("/", 1)[1]: tar.extractfile(m).read().decode() for m in tar.getmembers()}
    finally:
        proc.terminate()
        proc.wait(10)
    board = json.loads(files["board.json"])
    assert board["status"]["odr_hz"] == 6667 and board["sample_rate_hz"] > 3000, board
    assert board["counters"]["crc_errors"] == 0 and board["counters"]["good_packets"] > 0
    assert "board's stream" in files["doctor.txt"] and "packets" in files["doctor.txt"], files["doctor.txt"]
