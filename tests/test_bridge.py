"""`tecdard doctor` on the USB-serial bridge (issue 49): which bridge a port is (sysfs), the link and the
baud against it and the firmware, the FTDI latency timer, and whether the bytes at that baud are frames."""
from __future__ import annotations

import os
import pathlib

import numpy as np

from tecdard.drivers import imu_wire
from tecdard.drivers.bridge import check_bridge, check_stream, port_info

RULE = pathlib.Path(__file__).resolve().parents[1] / "systemd" / "99-tecdar-imu.rules"


def _sysfs(root: pathlib.Path, tty: str, vid: str, pid: str, product: str, latency: int | None) -> str:
    """A scratch sysfs with one USB-serial tty, and a /dev link to it as the udev rule makes: the link."""
    usb = root / "sys" / "devices" / "pci0000:00" / "usb1" / "1-1"
    port = usb / "1-1:1.0" / tty
    port.mkdir(parents=True)
    (usb / "idVendor").write_text(vid + "\n")
    (usb / "idProduct").write_text(pid + "\n")
    (usb / "product").write_text(product + "\n")
    if latency is not None:
        (port / "latency_timer").write_text(f"{latency}\n")
    cls = root / "sys" / "class" / "tty" / tty
    cls.mkdir(parents=True)
    os.symlink(port, cls / "device")
    dev = root / "dev"
    dev.mkdir()
    (dev / tty).write_text("")
    os.symlink(dev / tty, dev / "tecdar-imu")
    return str(dev / "tecdar-imu")


def test_an_ftdi_bridge_at_16_ms_is_told_to_take_1(tmp_path):
    port = _sysfs(tmp_path, "ttyUSB0", "0403", "6014", "Single RS232-HS", 16)
    info = port_info(port, str(tmp_path / "sys"))
    assert (info.vid, info.pid, info.latency_timer_ms) == (0x0403, 0x6014, 16)
    checks = check_bridge(port, "uart", 2_000_000, str(tmp_path / "sys"))
    assert [c.status for c in checks] == ["pass", "warn"], checks
    assert "FT232H" in checks[0].detail and "16 ms" in checks[1].detail
    assert "/sys/bus/usb-serial/devices/ttyUSB0/latency_timer" in checks[1].fix
    (pathlib.Path(os.path.realpath(tmp_path / "sys/class/tty/ttyUSB0/device")) / "latency_timer").write_text("1\n")
    assert [c.status for c in check_bridge(port, "uart", 2_000_000, str(tmp_path / "sys"))] == ["pass", "pass"]


def test_a_bridge_with_the_wrong_link_or_a_baud_it_cannot_carry(tmp_path):
    sys_root = str(tmp_path / "sys")
    port = _sysfs(tmp_path, "ttyUSB0", "10c4", "ea60", "CP2102 USB to UART Bridge Controller", None)
    (c,) = check_bridge(port, "uart", 2_000_000, sys_root)
    assert c.status == "fail" and "CP2102 (not N)" in c.detail and "921600" in c.detail
    (c,) = check_bridge(port, "usb-cdc", 115_200, sys_root)
    assert c.status == "warn" and "link: uart" in c.fix


def test_a_ch343_at_another_baud_than_the_firmwares(tmp_path):
    port = _sysfs(tmp_path, "ttyACM0", "1a86", "55d3", "USB Single Serial", None)
    (c,) = check_bridge(port, "uart", 1_000_000, str(tmp_path / "sys"))
    assert c.status == "warn" and "CH343" in c.detail and "2000000" in c.fix


def test_a_port_sysfs_does_not_know_is_skipped(tmp_path):
    (c,) = check_bridge("/dev/null", "uart", 2_000_000, str(tmp_path))
    assert c.status == "skip"


class _Link:
    def __init__(self, data: bytes):
        self.data, self.closed = data, False

    def read(self, n: int) -> bytes:
        out, self.data = self.data[:n], self.data[n:]
        return out

    def close(self) -> None:
        self.closed = True


def test_the_stream_at_the_right_baud_and_at_a_wrong_one():
    raw = np.zeros((8, 6), dtype=np.int16)
    good = b"".join(imu_wire.encode_samples(k * 8, 1000 * k, raw) for k in range(20))
    c = check_stream("/dev/x", 2_000_000, seconds=0.05, opener=lambda: _Link(good))
    assert c.status == "pass" and "20 packets, 160 samples" in c.detail
    # the same bytes clocked at another baud arrive as noise: no frame passes its CRC
    garbled = bytes(np.random.default_rng(1).integers(0, 256, len(good), dtype=np.uint8))
    c = check_stream("/dev/x", 2_000_000, seconds=0.05, opener=lambda: _Link(garbled))
    assert c.status == "fail" and "no frame passed its CRC" in c.detail
    c = check_stream("/dev/x", 2_000_000, seconds=0.05, opener=lambda: _Link(b""))
    assert c.status == "fail" and "no bytes" in c.detail

    def busy():
        raise OSError("[Errno 16] Device or resource busy")
    assert check_stream("/dev/x", 2_000_000, opener=busy).status == "skip"


def test_the_udev_rule_names_every_bridge_and_the_latency_timer():
    rule = RULE.read_text()
    for vid, pid in (("0403", "6014"), ("0403", "6010"), ("0403", "6015"), ("10c4", "ea60"), ("1a86", "55d3")):
        assert f'ATTRS{{idVendor}}=="{vid}", ATTRS{{idProduct}}=="{pid}", SYMLINK+="tecdar-imu"' in rule
    assert 'DRIVER=="ftdi_sio", ATTR{latency_timer}="1"' in rule
    active = [ln for ln in rule.splitlines() if ln and not ln.startswith("#")]
    assert not any("0483" in ln for ln in active)          # USB-CDC is future work, not a shipped match
