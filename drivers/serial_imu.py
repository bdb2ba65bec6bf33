"""The fingertip board over USB-CDC (pyserial): bytes -> `tecdar-imu/1` packets -> timestamped SI samples."""
from __future__ import annotations

import collections
import grp
import os
import pwd
import select
import time
from dataclasses import dataclass

import numpy as np
import serial
import serial.tools.list_ports

from tecdard.drivers.imu_source import ImuSource
from tecdard.drivers.imu_wire import (FLAG_SELF_TEST_FAILED, FLAG_SENSOR_ABSENT, IdentityPacket, SamplesPacket,
                                      StatusPacket, WireParser, frame_bytes)
from tecdard.drivers.lsm6dsr import (DEFAULT_ACCEL_FS_G, DEFAULT_GYRO_FS_DPS, DEFAULT_ODR_HZ, PARTS, Scaling,
                                     odr_problem, part_name)
from tecdard.drivers.timesync import ClockSync, Unwrapper
from tecdard.host import Check
from tecdard.options import option, read_options

READ_CHUNK_BYTES = 1 << 16
RETRY_MIN_S = 0.05
RETRY_MAX_S = 2.0
MIN_STEP_S = 1e-6          # output times are strictly increasing by at least this
LINKS = ("usb-cdc", "uart")
UART_BITS_PER_BYTE = 10    # start, 8 data, stop


class PortError(OSError):
    """The port cannot be opened; the message says which and why, in one line."""


@dataclass
class SerialParams:
    """The `imu.serial` section: the fingertip board on a serial port (docs/imu-serial.md)."""
    port: str | None = option(None, "the board's device: the udev rule's link (/dev/tecdar-imu), /dev/ttyACM0 or "
                                    "/dev/serial/by-id/...; or give vid_pid", kind="optstr")
    vid: int | None = None            # from vid_pid
    pid: int | None = None
    serial_number: str | None = option(None, "with vid_pid: the board's USB serial number, where several match",
                                       kind="optstr")
    baud: int = option(2_000_000, "the UART's rate behind a USB-serial bridge (USB-CDC ignores it)", unit="baud",
                       minval=1200)
    link: str = option("uart", "uart: a UART at `baud` behind a USB-serial bridge, as the reference board (its "
                               "wire time known); usb-cdc: a board with its own USB port (none shipped)",
                       choices=LINKS)
    odr_hz: int = option(DEFAULT_ODR_HZ, "the data rate assumed until the board's first status packet", unit="Hz",
                         minval=1, maxval=65535)
    gyro_fs_dps: int = option(DEFAULT_GYRO_FS_DPS, "the gyro's full scale assumed until the first status packet",
                              unit="dps")
    accel_fs_g: int = option(DEFAULT_ACCEL_FS_G, "the accelerometer's full scale assumed until the first status "
                                                 "packet", unit="g")
    vid_pid: str | None = option(None, "instead of port: the board's USB vendor and product id, hex VID:PID such as "
                                       "0403:6014", kind="optstr")

    @classmethod
    def from_config(cls, section) -> "SerialParams":
        p = read_options(cls, section)
        if p.vid_pid:
            try:
                vid_s, pid_s = p.vid_pid.split(":")
                p.vid, p.pid = int(vid_s, 16), int(pid_s, 16)
            except ValueError:
                raise section.error("vid_pid", f"expected hex VID:PID such as 0403:6014, got {p.vid_pid!r}") from None
        if p.port is None and p.vid is None:
            raise section.error("port", "give a port path or vid_pid")
        try:
            Scaling(p.gyro_fs_dps, p.accel_fs_g)
        except ValueError as exc:         # "gyro_fs_dps: ...": the key, then the problem
            key, _, what = str(exc).partition(": ")
            raise section.error(key, what) from None
        problem = odr_problem(p.odr_hz)
        if problem:                       # "odr_hz 1234 is not ...": the key, then the problem
            raise section.error("odr_hz", problem.split(" ", 1)[1])
        return p


def find_port(vid: int, pid: int, serial_number: str | None = None, comports=None) -> str:
    """The device path of the connected USB serial device vid:pid (and serial number), or PortError.
    `comports`: what lists the ports (pyserial's by default)."""
    for info in (comports or serial.tools.list_ports.comports)():
        if info.vid == vid and info.pid == pid and (serial_number is None or info.serial_number == serial_number):
            return info.device
    sn = f" serial {serial_number}" if serial_number else ""
    raise PortError(f"no USB serial device {vid:04x}:{pid:04x}{sn} is connected")


class SerialImuSource(ImuSource):
    """The fingertip board: `read(timeout)` -> (t, gyro, accel) or None (drivers.imu_source.ImuSource).

    t is the host's monotonic clock (s); gyro rad/s and accel m/s^2 in the IMU frame.
    If the port vanishes (unplug), the source reports a `fault` event, retries opening with
    back-off, and resumes; nothing above it restarts. Events wait in `events` for the owner
    to forward (the acquisition thread never touches other state).
    """

    def __init__(self, params: SerialParams, clock=time.monotonic):
        self.params = params
        self.clock = clock
        self.parser = WireParser()
        self.scaling = Scaling(params.gyro_fs_dps, params.accel_fs_g)
        self.odr_hz = float(params.odr_hz)
        self.unwrap = Unwrapper()
        self.sync = ClockSync()
        self.ser: serial.Serial | None = None
        self.events: collections.deque = collections.deque(maxlen=100)
        self.disconnects = 0
        self.reconnects = 0
        self.status: StatusPacket | None = None
        self.who_am_i: int | None = None         # the sensor's, from the board's identity packet
        self._lost: tuple[float, str] | None = None      # (when, why) the port was lost, until it is back
        self.latest: tuple[float, np.ndarray, np.ndarray] | None = None
        self._retry_at = 0.0
        self._last_t: float | None = None        # the last sample time handed on (host clock)
        self._last_mcu: float | None = None      # the board's time of the last sample read
        self.clock_steps = 0                     # the board's clock stepped back (re-anchored)
        self._retry_s = RETRY_MIN_S
        self.port_path: str | None = None
        self._steps_key: tuple | None = None
        self._steps = np.zeros(0)

    # -- port -----------------------------------------------------------------
    def _resolve(self) -> str:
        if self.params.port:
            return self.params.port
        return find_port(self.params.vid, self.params.pid, self.params.serial_number)

    def open(self) -> None:
        """Open the port now; PortError with a one-line reason if it cannot be."""
        path = self._resolve()
        try:
            self.ser = serial.Serial(path, baudrate=self.params.baud, timeout=0.05)
        except (serial.SerialException, OSError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc).split(":")[-1].strip() or type(exc).__name__
            raise PortError(f"cannot open {path}: {reason}") from None
        self.port_path = path

    def start(self) -> str | None:
        """Open the port now; where it cannot be, say why and keep trying in the background (a fault
        until it opens)."""
        try:
            self.open()
        except PortError as exc:
            self.mark_lost(str(exc))
            return f"{exc}; retrying in the background"
        return None

    def close(self) -> None:
        if self.ser is not None:
            try:
                self.ser.close()
            except Exception:
                pass
            self.ser = None

    def mark_lost(self, why: str) -> None:
        self.close()
        self._lost = (self.clock(), why)
        self.disconnects += 1
        self.parser.reset_sequence()
        self.events.append({"kind": "fault", "code": "imu_disconnected", "message": f"IMU port lost: {why}"})
        self._retry_s = RETRY_MIN_S
        self._retry_at = self.clock() + self._retry_s

    def _try_reopen(self) -> bool:
        now = self.clock()
        if now < self._retry_at:
            return False
        try:
            self.open()
        except PortError:
            self._retry_s = min(self._retry_s * 2, RETRY_MAX_S)
            self._retry_at = now + self._retry_s
            return False
        self.reconnects += 1
        self._lost = None
        self.unwrap.reset()
        self.sync.reset()
        self._last_mcu = None
        self.events.append({"kind": "fault_cleared", "code": "imu_disconnected",
                            "message": f"IMU port {self.port_path} back"})
        return True

    # -- reading --------------------------------------------------------------
    def read(self, timeout: float = 0.05):
        if self.ser is None:
            if not self._try_reopen():
                time.sleep(min(timeout, max(0.0, self._retry_at - self.clock())) or 0.001)
                return None
        try:
            data = self._read_available(timeout)
        except (serial.SerialException, OSError) as exc:
            self.mark_lost(str(exc).split("(")[0].strip() or type(exc).__name__)
            return None
        if not data:
            return None
        return self.decode(data, self.clock())

    def _read_available(self, timeout: float) -> bytes:
        """Whatever has arrived, after waiting up to `timeout` for the first byte: one select and one
        read on the port's descriptor (a board's packet every 1.2 ms wakes this 840 times a second;
        pyserial's read(1), in_waiting and read(n) were three system calls and a tcsetattr for its
        timeout each time). A port without a descriptor is read through pyserial."""
        try:
            fd = self.ser.fileno()
        except (AttributeError, NotImplementedError, serial.SerialException):
            fd = None
        if fd is None:
            if self.ser.timeout != timeout:
                self.ser.timeout = timeout
            data = self.ser.read(1)
            waiting = self.ser.in_waiting
            return data + self.ser.read(min(waiting, READ_CHUNK_BYTES)) if waiting else data
        ready, _, _ = select.select([fd], [], [], timeout)
        if not ready:
            return b""
        data = os.read(fd, READ_CHUNK_BYTES)
        if not data:             # readable, yet nothing: the device went away (pyserial says the same)
            raise serial.SerialException("device reports readiness to read but returned no data")
        return data

    def decode(self, data: bytes, host_s: float):
        """Bytes that arrived at host time host_s -> (t, gyro, accel) or None (no samples in them)."""
        ts, raws = [], []
        pkts = self.parser.feed(data)
        # On a UART link a packet's bytes take their time on the wire (110 bytes at 2 Mbaud: 0.55 ms), and the
        # bytes after it in this read more: each packet is dated to when its first byte left the board, so that
        # the clock fit does not take the wire time for the board's clock offset.
        wire_s = [0.0] * len(pkts)
        if self.params.link == "uart":
            s_per_byte, behind = UART_BITS_PER_BYTE / self.params.baud, 0
            for i in range(len(pkts) - 1, -1, -1):
                behind += frame_bytes(pkts[i])
                wire_s[i] = behind * s_per_byte
        for pkt, wire in zip(pkts, wire_s):
            if isinstance(pkt, StatusPacket):
                # every field against the protocol's ranges before any is used: a status naming a
                # range or a rate the chip has not is counted and ignored whole
                problem = odr_problem(pkt.odr_hz)
                if problem is None:
                    try:
                        Scaling(pkt.gyro_fs_dps, pkt.accel_fs_g, self.scaling.part)
                    except ValueError as exc:
                        problem = str(exc)
                if problem is not None:
                    self.parser.counters.bad_status += 1
                    if self.parser.counters.bad_status == 1:
                        self.events.append({"kind": "warning", "code": "imu_bad_status",
                                            "message": f"IMU status packet ignored: {problem}"})
                    continue
                self._flags_changed(self.status, pkt)
                self.status = pkt
                self.scaling.set(pkt.gyro_fs_dps, pkt.accel_fs_g)
                self.odr_hz = float(pkt.odr_hz)
            elif isinstance(pkt, IdentityPacket):
                if pkt.who_am_i != self.who_am_i:
                    self._identified(pkt.who_am_i)
            elif isinstance(pkt, SamplesPacket):
                if pkt.restart:
                    self._restarted()
                ts.append(self._packet_times(pkt, host_s - wire))
                raws.append(pkt.raw)
        if not raws:
            return None
        # one packet a read is the usual case (a board's packet every 1.2 ms)
        t = self._increasing(ts[0] if len(ts) == 1 else np.concatenate(ts))
        gyro, accel = self.scaling.to_si(raws[0] if len(raws) == 1 else np.concatenate(raws))
        self.latest = (float(t[-1]), gyro[-1].copy(), accel[-1].copy())
        return t, gyro, accel

    def _restarted(self) -> None:
        """The board started again (its seq went back or jumped): its clock did too, so the time fit
        starts again from the next packet; nothing was lost."""
        self.unwrap.reset()
        self.sync.reset()
        self._last_mcu = None
        self.events.append({"kind": "warning", "code": "imu_board_restart",
                            "message": f"the IMU board restarted ({self.parser.counters.restarts} so far); "
                                       "its clock is fitted afresh"})

    @property
    def part(self) -> str | None:
        """The sensor the board found ("LSM6DSR", "LSM6DSO/LSM6DSOX", or what else answered), None until the
        board's first identity packet (a board older than the packet never says)."""
        return part_name(self.who_am_i)

    def _identified(self, who_am_i: int) -> None:
        """The board said which sensor answered: its ranges check the statuses from now on, and a configured
        range the part lacks (used only until the first status) is said once."""
        self.who_am_i = who_am_i
        part = PARTS.get(who_am_i)
        if part is None:
            self.events.append({"kind": "warning", "code": "imu_unknown_part",
                                "message": f"the IMU board read WHO_AM_I {who_am_i:#04x} from its sensor: not an "
                                           "LSM6DSR (0x6b) or LSM6DSO/LSM6DSOX (0x6c); check the part and its SPI wiring"})
            return
        self.scaling.part = part
        if self.params.gyro_fs_dps not in part.gyro_fs_dps or self.params.accel_fs_g not in part.accel_fs_g:
            self.events.append({"kind": "warning", "code": "imu_config_range",
                                "message": f"the IMU board carries an {part.name}, which has no "
                                           f"{self.params.gyro_fs_dps} dps / {self.params.accel_fs_g} g range: "
                                           "set imu.serial.gyro_fs_dps and accel_fs_g to the ranges its status "
                                           f"reports (gyro {', '.join(map(str, part.gyro_fs_dps))} dps)"})

    def _flags_changed(self, old: StatusPacket | None, new: StatusPacket) -> None:
        """A status whose flags say something new: the sensor not answering is a fault until a status
        says it answers; a failed self-test is a warning, said once each time the board reports it."""
        was = 0 if old is None else old.flags
        if new.flags & FLAG_SENSOR_ABSENT and not was & FLAG_SENSOR_ABSENT:
            self.events.append({"kind": "fault", "code": "imu_sensor_absent",
                                "message": "the IMU board says its sensor does not answer (no LSM6DSR or LSM6DSO "
                                           "WHO_AM_I, or no reply): check the sensor's SPI wiring and supply"})
        elif was & FLAG_SENSOR_ABSENT and not new.flags & FLAG_SENSOR_ABSENT:
            self.events.append({"kind": "fault_cleared", "code": "imu_sensor_absent",
                                "message": "the IMU board's sensor answers again"})
        if new.flags & FLAG_SELF_TEST_FAILED and not was & FLAG_SELF_TEST_FAILED:
            self.events.append({"kind": "warning", "code": "imu_self_test_failed",
                                "message": "the IMU board's sensor failed its self-test at start: its samples "
                                           "may be wrong; replace the fingertip's sensor"})

    def _packet_times(self, pkt: SamplesPacket, host_s: float) -> np.ndarray:
        """One packet's sample times on the host's clock, mapped as it arrives: a clock sync that
        re-anchors at this packet never moves the packets before it.

        The board's clock stepping back (a glitch, or the board restarting its clock: the
        packet's first sample is not after the last one's) re-anchors the mapping here, at once:
        the samples keep coming and are mapped by their arrival. Waiting for ClockSync to see a
        run of late packets left them mapped up to the step into the past (2 s for a reset, and
        `imu_stale` while they streamed). Each step is counted (`clock_steps`) and said once."""
        n = len(pkt.raw)
        t0 = self.unwrap(pkt.t0_us)
        if self._last_mcu is not None and t0 <= self._last_mcu:
            self.clock_steps += 1
            step_ms = (self._last_mcu - t0) * 1e3
            if self.clock_steps == 1:
                self.events.append({"kind": "warning", "code": "imu_clock_step",
                                    "message": f"the IMU board's clock stepped back {step_ms:.1f} ms (a glitch or "
                                               "a restart of the board); its times are re-anchored to their arrival"})
            self.sync.reset()
        if self._steps_key != (n, self.odr_hz):       # the sample offsets within a packet, s (made once)
            self._steps_key, self._steps = (n, self.odr_hz), np.arange(n) / self.odr_hz
        mcu = t0 + self._steps
        self._last_mcu = float(mcu[-1])
        self.sync.add(mcu[-1], host_s)
        return self.sync.to_host(mcu)

    def _increasing(self, t: np.ndarray) -> np.ndarray:
        """Every sample after the one before it, checked sample by sample (the fit moves as its
        lower envelope is learned, and re-anchors on a clock step): a time at or before the last
        one handed on is moved to just after it."""
        prev = -np.inf if self._last_t is None else self._last_t
        if t[0] > prev and (len(t) == 1 or bool((t[1:] > t[:-1]).all())):
            self._last_t = float(t[-1])            # the usual packet: already increasing
            return t
        floor = np.maximum.accumulate(np.concatenate([[prev], t]))[:-1]
        bad = t <= floor
        if bad.any():                              # rare: at a re-anchor's seam
            t = t.copy()
            for i in range(int(np.argmax(bad)), len(t)):
                t[i] = max(t[i], (t[i - 1] if i else prev) + MIN_STEP_S)
        self._last_t = float(t[-1])
        return t

    @property
    def saturation(self) -> tuple[float, float]:
        """(gyro rad/s, accel m/s^2) at which a sample is clipped, at the full scales in use."""
        return self.scaling.saturation

    def counters(self) -> dict:
        out = self.parser.counters.as_dict()
        out.update(disconnects=self.disconnects, reconnects=self.reconnects, clock_resets=self.sync.resets,
                   clock_steps=self.clock_steps)
        return out

    def faults(self) -> dict[str, str]:
        out = {}
        lost = self._lost
        if lost is not None:
            out["imu_disconnected"] = (f"the board's port {self.port_path or self.params.port or ''} was lost "
                                       f"{self.clock() - lost[0]:.1f} s ago ({lost[1]}); reopened every "
                                       f"{self._retry_s:g} s at most")
        if self.status is not None and self.status.flags & FLAG_SENSOR_ABSENT:
            out["imu_sensor_absent"] = "the board says its sensor does not answer (check its SPI wiring and supply)"
        return out

    def lost_s(self) -> float | None:
        lost = self._lost
        return None if lost is None else round(self.clock() - lost[0], 1)

    def drain_events(self) -> list[dict]:
        out = list(self.events)
        self.events.clear()
        return out

    def checks(self) -> list[Check]:
        """The board at its port; then its bridge (the link, the baud, the FTDI latency timer) and
        whether what arrives at that baud is frames (drivers/bridge.py)."""
        from tecdard.drivers.bridge import check_bridge, check_stream
        path, board = board_check(self.params)
        if path is None:
            return [board]
        return [board, *check_bridge(path, self.params.link, self.params.baud), check_stream(path, self.params.baud)]


def _access_problem(path: str) -> tuple[str, str] | None:
    """None, or (what is wrong, the device's group)."""
    if os.access(path, os.R_OK | os.W_OK):
        return None
    st = os.stat(path)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    user = pwd.getpwuid(os.getuid()).pw_name
    return f"{path} is mode {st.st_mode & 0o777:o}, group {group}, and {user} may not read and write it", group


def check_board(serial_params: "SerialParams", comports=None) -> Check:
    """The board at its configured port (by path, or found by VID:PID) and readable and writable."""
    return board_check(serial_params, comports)[1]


def board_check(serial_params: "SerialParams", comports=None) -> tuple[str | None, Check]:
    """check_board's finding, with the port's path where it passed (None otherwise)."""
    if comports is None:
        import serial.tools.list_ports
        comports = serial.tools.list_ports.comports
    p = serial_params
    if p.port is not None:
        path = p.port
        if not os.path.exists(path):
            fix = ("plug the board in; with the udev rule installed it appears as /dev/tecdar-imu"
                   if "tecdar-imu" in path else "plug the board in, or correct imu.serial.port")
            return None, Check("fingertip board", "fail", f"{path} does not exist", fix)
    else:
        try:
            path = find_port(p.vid, p.pid, p.serial_number, comports)
        except PortError as exc:
            seen = ", ".join(f"{i.device} {i.vid:04x}:{i.pid:04x}" for i in comports() if i.vid is not None)
            return None, Check("fingertip board", "fail", f"{exc}" + (f" (connected: {seen})" if seen else ""),
                         "plug the board in, or correct imu.serial.vid_pid (`lsusb` lists the IDs)")
    problem = _access_problem(path)
    if problem is not None:
        detail, group = problem
        return None, Check("fingertip board", "fail", detail,
                     f"`sudo usermod -aG {group} $USER` and log in again (the unit runs with "
                     f"SupplementaryGroups={group}); the udev rule sets the group")
    return path, Check("fingertip board", "pass", f"{path} (real path {os.path.realpath(path)}) readable and writable")

