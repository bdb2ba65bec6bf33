"""The USB-serial bridge between the fingertip board's UART and the host (docs/firmware.md): which one a
port is, from sysfs, and `tecdard doctor`'s checks of it: the link setting, the baud rate against what
the bridge and the firmware do, the FTDI latency timer, and whether the bytes at that baud are frames.

Every function reads the host through arguments with the real defaults (`sys_root`), so the tests can
point them at a scratch tree shaped like sysfs."""
from __future__ import annotations

import os
import pathlib
import time
from dataclasses import dataclass

from tecdard.host import Check

FIRMWARE_BAUD = 2_000_000          # the reference firmware's USART1 (firmware/board/stm32f405)
LATENCY_TIMER_MS = 1               # what the udev rule sets; the FTDI default is 16


@dataclass(frozen=True)
class Bridge:
    """A USB-serial bridge the board may sit behind: its name and the highest baud it carries."""
    name: str
    max_baud: int
    ftdi: bool = False


# VID:PID -> the bridge. From each vendor's datasheet: FT232H and FT2232H 12 Mbaud, FT-X and FT232R
# 3 Mbaud; CP2102N 3 Mbaud (the older CP2102 on the same ID: 921.6 kbaud, told apart by its product
# string); CH343 6 Mbaud; CH340 2 Mbaud.
BRIDGES = {
    (0x0403, 0x6014): Bridge("FTDI FT232H", 12_000_000, ftdi=True),
    (0x0403, 0x6010): Bridge("FTDI FT2232H", 12_000_000, ftdi=True),
    (0x0403, 0x6015): Bridge("FTDI FT-X (FT230X/FT231X)", 3_000_000, ftdi=True),
    (0x0403, 0x6001): Bridge("FTDI FT232R", 3_000_000, ftdi=True),
    (0x10C4, 0xEA60): Bridge("Silicon Labs CP2102N", 3_000_000),
    (0x1A86, 0x55D3): Bridge("WCH CH343", 6_000_000),
    (0x1A86, 0x7523): Bridge("WCH CH340", 2_000_000),
}
CP2102_CLASSIC = Bridge("Silicon Labs CP2102 (not N)", 921_600)


@dataclass
class PortInfo:
    """What sysfs says of a tty: its USB IDs and product string (None where it is not USB), and the
    FTDI latency timer (ms; None where there is none)."""
    tty: str
    vid: int | None = None
    pid: int | None = None
    product: str = ""
    latency_timer_ms: int | None = None

    def bridge(self) -> Bridge | None:
        if self.vid is None or self.pid is None:
            return None
        b = BRIDGES.get((self.vid, self.pid))
        if b is not None and (self.vid, self.pid) == (0x10C4, 0xEA60) and "CP2102N" not in self.product \
                and "CP2102" in self.product:
            return CP2102_CLASSIC
        return b


def port_info(port: str, sys_root: str = "/sys") -> PortInfo:
    """sysfs's view of the tty a port path (a link such as /dev/tecdar-imu, or the node) names."""
    tty = os.path.basename(os.path.realpath(port))
    info = PortInfo(tty)
    dev = pathlib.Path(sys_root, "class", "tty", tty, "device")
    if not dev.exists():
        return info
    here = pathlib.Path(os.path.realpath(dev))
    lt = here / "latency_timer"
    if lt.is_file():
        try:
            info.latency_timer_ms = int(lt.read_text().strip())
        except (OSError, ValueError):
            pass
    for d in (here, *here.parents):            # the USB device is the first ancestor with the IDs
        if (d / "idVendor").is_file() and (d / "idProduct").is_file():
            try:
                info.vid = int((d / "idVendor").read_text().strip(), 16)
                info.pid = int((d / "idProduct").read_text().strip(), 16)
                info.product = (d / "product").read_text().strip() if (d / "product").is_file() else ""
            except (OSError, ValueError):
                info.vid = info.pid = None
            break
        if d == pathlib.Path(sys_root):
            break
    return info


def check_bridge(port: str, link: str, baud: int, sys_root: str = "/sys") -> list[Check]:
    """The bridge at `port` against the config's `link` and `baud`, and its latency timer."""
    info = port_info(port, sys_root)
    b = info.bridge()
    if info.vid is None:
        return [Check("USB-serial bridge", "skip", f"{port}: not a USB device sysfs knows (a pseudo-terminal?)")]
    ids = f"{info.vid:04x}:{info.pid:04x}"
    if b is None:
        if link == "uart":
            return [Check("USB-serial bridge", "warn", f"{port} is {ids} ({info.product or 'no product string'}), "
                          "not a bridge we know: its highest baud and latency are unchecked",
                          "an FTDI FT232H/FT2232H/FT-X, a CP2102N or a CH343 is known to carry 2 Mbaud "
                          "(docs/firmware.md)")]
        return [Check("USB-serial bridge", "pass", f"{port} is {ids} ({info.product or 'USB-CDC'}), link usb-cdc")]
    out = []
    if link != "uart":
        out.append(Check("USB-serial bridge", "warn", f"{port} is a {b.name} ({ids}) but imu.serial.link is {link}: "
                         "the packets are dated without their time on the wire",
                         "set imu.serial.link: uart (the reference firmware's UART is behind this bridge)"))
    elif baud > b.max_baud:
        out.append(Check("USB-serial bridge", "fail", f"{port} is a {b.name} ({ids}), which carries at most "
                         f"{b.max_baud} baud; imu.serial.baud is {baud}",
                         f"use a bridge that does {FIRMWARE_BAUD} baud (FT232H, CP2102N, CH343: docs/firmware.md)"))
    elif baud != FIRMWARE_BAUD:
        out.append(Check("USB-serial bridge", "warn", f"{port} is a {b.name} ({ids}); imu.serial.baud is {baud}, "
                         f"the reference firmware sends at {FIRMWARE_BAUD}",
                         f"set imu.serial.baud: {FIRMWARE_BAUD}, unless your board's firmware was built for {baud}"))
    else:
        out.append(Check("USB-serial bridge", "pass", f"{port} is a {b.name} ({ids}) at {baud} baud, link uart"))
    if b.ftdi:
        lt = info.latency_timer_ms
        fix = (f"install the udev rule (systemd/99-tecdar-imu.rules sets it), or now: echo {LATENCY_TIMER_MS} | "
               f"sudo tee /sys/bus/usb-serial/devices/{info.tty}/latency_timer")
        if lt is None:
            out.append(Check("FTDI latency timer", "warn", f"{info.tty}: no latency_timer in sysfs", fix))
        elif lt > LATENCY_TIMER_MS:
            out.append(Check("FTDI latency timer", "warn", f"{info.tty}: {lt} ms: each packet may wait that long "
                             "in the bridge before it is sent on", fix))
        else:
            out.append(Check("FTDI latency timer", "pass", f"{info.tty}: {lt} ms"))
    return out


def check_stream(port: str, baud: int, seconds: float = 0.5, opener=None) -> Check:
    """Whether what arrives at `port` at `baud` for `seconds` is tecdar-imu/1 frames: a wrong baud
    rate reads as bytes with no frame that passes its CRC."""
    from tecdard.drivers.imu_wire import WireParser
    if opener is None:
        import serial

        def opener():
            return serial.Serial(port, baud, timeout=0.05, exclusive=False)
    try:
        link = opener()
    except (OSError, ValueError) as exc:
        return Check("board's stream", "skip", f"{port}: cannot open it ({exc}); is the daemon holding it?")
    parser = WireParser()
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            data = link.read(4096)
            if data:
                parser.feed(data)
    except OSError as exc:
        return Check("board's stream", "fail", f"{port}: reading failed ({exc})", "check the cable and the board")
    finally:
        link.close()
    c = parser.counters
    if c.bytes_in == 0:
        return Check("board's stream", "fail", f"{port}: no bytes in {seconds:g} s",
                     "is the board powered and flashed? Its TX goes to the bridge's RX (docs/firmware.md)")
    if c.good_packets == 0:
        return Check("board's stream", "fail", f"{port}: {c.bytes_in} bytes in {seconds:g} s and no frame passed "
                     f"its CRC ({c.crc_errors} CRC errors): a baud rate other than {baud}?",
                     f"imu.serial.baud must be the firmware's ({FIRMWARE_BAUD} for the reference firmware)")
    bad = c.crc_errors + c.malformed
    status = "pass" if bad == 0 else "warn"
    return Check("board's stream", status, f"{port}: {c.good_packets} packets, {c.samples} samples in "
                 f"{seconds:g} s at {baud} baud; {c.crc_errors} CRC errors, {c.malformed} malformed",
                 None if bad == 0 else "errors on the line: a long or unshielded cable, or a marginal baud rate")
