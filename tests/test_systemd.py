"""systemd integration: READY=1 and WATCHDOG=1 on $NOTIFY_SOCKET, and a sane unit file."""
import configparser
import socket

from tests.conftest import ROOT

WATCHDOG_USEC = 400_000


def test_notify_ready_and_watchdog(make_daemon, tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(30.0)
    try:
        d = make_daemon(env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": str(WATCHDOG_USEC)})
        seen = []
        while seen.count("WATCHDOG=1") < 3:
            seen.append(sock.recv(256).decode())
        assert "READY=1" in seen
        assert seen.index("READY=1") < len(seen) - 1
        d.terminate()
        sock.settimeout(5.0)
        rest = []
        try:
            while "STOPPING=1" not in rest:
                rest.append(sock.recv(256).decode())
        except socket.timeout:
            pass
        assert "STOPPING=1" in rest
    finally:
        sock.close()


def test_unit_file_declares_notify_watchdog_and_hardening():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(ROOT / "systemd" / "tecdard.service")
    svc = unit["Service"]
    assert svc["Type"] == "notify"
    assert svc["WatchdogSec"] and svc["Restart"] == "on-failure"
    assert svc["NoNewPrivileges"] == "yes" and svc["ProtectSystem"] == "strict"
    assert "tecdard run --config" in svc["ExecStart"]
    text = (ROOT / "systemd" / "tecdard.service").read_text()
    assert "DeviceAllow=char-ttyACM rw" in text
    # numba finds no writable cache in a read-only install: it must be given one
    assert svc["CacheDirectory"] == "tecdar" and "NUMBA_CACHE_DIR=/var/cache/tecdar" in svc["Environment"]
