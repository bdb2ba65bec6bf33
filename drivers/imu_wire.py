"""`tecdar-imu/1` framing: CRC, packet encoding and a resynchronising parser. Pure logic, no I/O."""
from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, field

import numpy as np

SYNC = b"\xa5\x5a"
TYPE_SAMPLES = 0x01
TYPE_STATUS = 0x02
TYPE_IDENTITY = 0x03      # our extension: the sensor's WHO_AM_I after each status (a reader of the spec skips it)
MAX_LEN = 1024
HEADER_BYTES = 5          # sync (2), type (1), len (2)
CRC_BYTES = 2
SAMPLES_HEADER_BYTES = 7  # seq (2), t0_us (4), n (1)
SAMPLE_BYTES = 12
MAX_SAMPLES = 64
STATUS_BYTES = 6
IDENTITY_BYTES = 1        # who_am_i; a longer payload is a later board's: the first byte is read, the rest skipped
FLAG_FIFO_OVERRUN = 0x01
FLAG_SELF_TEST_FAILED = 0x02   # the sensor's self-test failed at the board's start
FLAG_SENSOR_ABSENT = 0x04      # the sensor did not answer (WHO_AM_I wrong or no reply): no samples follow
RESTART_SEQ_JUMP = 32768       # a seq that goes back, or forward by more than this, is a board restart


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0 (check '123456789' = 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame(ptype: int, payload: bytes) -> bytes:
    body = struct.pack("<BH", ptype, len(payload)) + payload
    return SYNC + body + struct.pack("<H", crc16(body))


def encode_samples(seq: int, t0_us: int, raw: np.ndarray) -> bytes:
    """A samples packet: raw (n, 6) int16 gx, gy, gz, ax, ay, az; seq and t0_us wrap."""
    n = len(raw)
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"n: {n} samples per packet, expected 1..{MAX_SAMPLES}")
    payload = struct.pack("<HIB", seq & 0xFFFF, t0_us & 0xFFFFFFFF, n) + np.asarray(raw, "<i2").tobytes()
    return frame(TYPE_SAMPLES, payload)


def encode_status(odr_hz: int, gyro_fs_dps: int, accel_fs_g: int, flags: int = 0) -> bytes:
    return frame(TYPE_STATUS, struct.pack("<HHBB", odr_hz, gyro_fs_dps, accel_fs_g, flags))


def encode_identity(who_am_i: int) -> bytes:
    return frame(TYPE_IDENTITY, bytes([who_am_i & 0xFF]))


@dataclass
class SamplesPacket:
    seq: int
    t0_us: int
    raw: np.ndarray            # (n, 6) int16
    restart: bool = False      # the board restarted before this packet (its seq went back or jumped)


@dataclass
class StatusPacket:
    odr_hz: int
    gyro_fs_dps: int
    accel_fs_g: int
    flags: int


@dataclass
class IdentityPacket:
    who_am_i: int              # as the board read it: 0x6B LSM6DSR, 0x6C LSM6DSO/DSOX, else a wrong or absent part
    payload_bytes: int = IDENTITY_BYTES


def frame_bytes(pkt: "SamplesPacket | StatusPacket | IdentityPacket") -> int:
    """The bytes of a decoded packet's whole frame on the wire."""
    if isinstance(pkt, SamplesPacket):
        payload = SAMPLES_HEADER_BYTES + SAMPLE_BYTES * len(pkt.raw)
    else:
        payload = pkt.payload_bytes if isinstance(pkt, IdentityPacket) else STATUS_BYTES
    return HEADER_BYTES + payload + CRC_BYTES


@dataclass
class Counters:
    """Every counter the spec asks for, per stream."""
    good_packets: int = 0
    samples: int = 0
    crc_errors: int = 0
    malformed: int = 0
    unknown_types: int = 0
    bytes_discarded: int = 0
    samples_lost: int = 0
    status_packets: int = 0
    identity_packets: int = 0   # our extension (type 0x03): the sensor's WHO_AM_I
    bad_status: int = 0         # status packets whose values are outside the protocol's ranges (ignored)
    fifo_overruns: int = 0
    restarts: int = 0           # board restarts seen in seq (not counted as lost samples)
    bytes_in: int = 0
    bytes_consumed: int = 0     # bytes of frames that passed the CRC

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class WireParser:
    """Feed bytes, get packets. Hunts for sync anywhere, checks the CRC, and on any failure
    resynchronises at the next sync after the failed frame's first byte, so a good packet
    that follows a bad one is never lost. Never raises on input."""

    counters: Counters = field(default_factory=Counters)

    def __post_init__(self):
        self._buf = bytearray()
        self._last_seq: int | None = None
        self._last_n = 0

    def reset_sequence(self) -> None:
        """Forget the last seq (after a reconnect the device may have restarted)."""
        self._last_seq = None
        self._last_n = 0

    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> list:
        c = self.counters
        c.bytes_in += len(data)
        buf = self._buf
        buf += data
        out = []
        pos = 0
        n_buf = len(buf)
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                # keep a trailing first sync byte: its partner may be in the next chunk
                keep = 1 if n_buf > pos and buf[-1] == SYNC[0] else 0
                c.bytes_discarded += n_buf - pos - keep
                pos = n_buf - keep
                break
            c.bytes_discarded += i - pos
            pos = i
            if n_buf - pos < HEADER_BYTES:
                break
            ptype = buf[pos + 2]
            length = buf[pos + 3] | (buf[pos + 4] << 8)
            if length > MAX_LEN:
                c.malformed += 1
                c.bytes_discarded += 1
                pos += 1
                continue
            end = pos + HEADER_BYTES + length + CRC_BYTES
            if end > n_buf:
                break                       # wait for the rest of the frame
            body = bytes(buf[pos + 2:end - CRC_BYTES])
            crc = buf[end - 2] | (buf[end - 1] << 8)
            if crc16(body) != crc:
                c.crc_errors += 1
                c.bytes_discarded += 1
                pos += 1                    # resync after this frame's first byte
                continue
            c.bytes_consumed += end - pos
            payload = body[3:]
            pkt = self._decode(ptype, payload)
            if pkt is not None:
                out.append(pkt)
            pos = end
        del buf[:pos]
        return out

    def _decode(self, ptype: int, payload: bytes):
        c = self.counters
        if ptype == TYPE_SAMPLES:
            if len(payload) < SAMPLES_HEADER_BYTES:
                c.malformed += 1
                return None
            seq, t0_us, n = struct.unpack_from("<HIB", payload)
            if not 1 <= n <= MAX_SAMPLES or len(payload) != SAMPLES_HEADER_BYTES + SAMPLE_BYTES * n:
                c.malformed += 1
                return None
            restart = False
            if self._last_seq is not None:
                step = (seq - self._last_seq) & 0xFFFF
                if step == 0 or step > RESTART_SEQ_JUMP:
                    c.restarts += 1          # the board started again: nothing was lost
                    restart = True
                elif step > 1:
                    c.samples_lost += (step - 1) * self._last_n
            self._last_seq, self._last_n = seq, n
            raw = np.frombuffer(payload, dtype="<i2", offset=SAMPLES_HEADER_BYTES).reshape(n, 6)
            c.good_packets += 1
            c.samples += n
            return SamplesPacket(seq, t0_us, raw, restart)
        if ptype == TYPE_STATUS:
            if len(payload) != STATUS_BYTES:
                c.malformed += 1
                return None
            odr, gfs, afs, flags = struct.unpack("<HHBB", payload)
            c.good_packets += 1
            c.status_packets += 1
            if flags & FLAG_FIFO_OVERRUN:
                c.fifo_overruns += 1
            return StatusPacket(odr, gfs, afs, flags)
        if ptype == TYPE_IDENTITY:
            if not payload:
                c.malformed += 1
                return None
            c.good_packets += 1
            c.identity_packets += 1
            return IdentityPacket(payload[0], len(payload))
        c.unknown_types += 1
        return None
