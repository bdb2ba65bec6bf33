"""A fingertip board in software: spec-conforming `tecdar-imu/1` streams, with injectable faults.

Used by the tests (on a pseudo-terminal) and by the simulator to drive the whole serial path.
"""
from __future__ import annotations

import collections
import errno
import os
import pathlib
import select
import subprocess
import threading
import time
import tty
from dataclasses import dataclass

import numpy as np

from tecdard.drivers import imu_wire as W
from tecdard.drivers.lsm6dsr import Scaling


@dataclass
class BoardParams:
    odr_hz: int = 6667
    samples_per_packet: int = 8
    gyro_fs_dps: int = 4000
    accel_fs_g: int = 16
    drift_ppm: float = 0.0            # MCU clock error: mcu = true * (1 + drift)
    t0_us: int = 0                    # MCU time at start (set near 2^32 to test wrapping)
    status_period_s: float = 1.0
    who_am_i: int | None = 0x6B       # the identity packet after each status (None: a board that sends none)


class Board:
    """Encodes samples as the firmware would: packets of n samples, seq and t0_us, a status packet
    at start and every second. `packets(gyro, accel)` returns bytes for a block of SI samples."""

    def __init__(self, params: BoardParams | None = None):
        self.params = params or BoardParams()
        self.scaling = Scaling(self.params.gyro_fs_dps, self.params.accel_fs_g)
        self.seq = 0
        self.sample_index = 0
        self._next_status_s = 0.0

    def mcu_us(self, sample_index: int) -> int:
        true_s = sample_index / self.params.odr_hz
        return int(round(self.params.t0_us + true_s * (1 + self.params.drift_ppm * 1e-6) * 1e6)) & 0xFFFFFFFF

    def status(self, flags: int = 0) -> bytes:
        """A status frame, and the identity frame the firmware sends after it."""
        out = W.encode_status(self.params.odr_hz, self.params.gyro_fs_dps, self.params.accel_fs_g, flags)
        return out if self.params.who_am_i is None else out + W.encode_identity(self.params.who_am_i)

    def packets(self, gyro: np.ndarray, accel: np.ndarray) -> list[bytes]:
        """One frame per packet (status frames interleaved once a second of samples)."""
        return self.packets_raw(self.scaling.to_raw(gyro, accel))

    def packets_raw(self, raw: np.ndarray) -> list[bytes]:
        """Frames for raw int16 samples (n, 6), as the chip produced them."""
        out = []
        n = self.params.samples_per_packet
        for k in range(0, len(raw), n):
            t_s = self.sample_index / self.params.odr_hz
            if t_s >= self._next_status_s:
                out.append(self.status())
                self._next_status_s += self.params.status_period_s
            chunk = raw[k:k + n]
            out.append(W.encode_samples(self.seq, self.mcu_us(self.sample_index), chunk))
            self.seq = (self.seq + 1) & 0xFFFF
            self.sample_index += len(chunk)
        return out


class PtyDevice:
    """A pseudo-terminal standing in for the USB-CDC port, reachable through a stable symlink.

    `unplug()` closes the pty (the reader gets an I/O error); `replug()` makes a new pty behind
    the same link path, as udev does for a real device.
    """

    def __init__(self, link_path: str | pathlib.Path):
        self.link = pathlib.Path(link_path)
        self.dropped_frames = 0
        self.master = None
        self.slave = None
        self.replug()

    def replug(self) -> None:
        self.master, self.slave = os.openpty()
        name = os.ttyname(self.slave)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        tmp = self.link.with_suffix(".tmp")
        if tmp.exists() or tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(name)
        tmp.replace(self.link)

    def unplug(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None
        if self.link.is_symlink():
            self.link.unlink()

    def _fd(self) -> int:
        """The master's descriptor, read once: `unplug` may run in another thread at any moment
        (a write on the closed descriptor then fails with OSError, as on a pulled cable)."""
        fd = self.master
        if fd is None:
            raise OSError(errno.ENODEV, "the emulated board is unplugged")
        return fd

    def write(self, data: bytes) -> None:
        """Blocking write of everything (for tests that inject exact byte sequences)."""
        fd = self._fd()
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                select.select([], [fd], [], 1.0)
                continue
            view = view[n:]

    def write_frames(self, frames: list[bytes]) -> int:
        """Write whole frames without blocking, as a board does: when the host does not read and
        the buffer is full, the rest are dropped (returns how many). A frame cut short by a
        partial write is dropped too, and the reader's parser resynchronises."""
        fd = self._fd()
        for i, fr in enumerate(frames):
            try:
                n = os.write(fd, fr)
            except BlockingIOError:
                self.dropped_frames += len(frames) - i
                return len(frames) - i
            if n < len(fr):
                self.dropped_frames += len(frames) - i
                return len(frames) - i
        return 0

    def close(self) -> None:
        self.unplug()


class StreamThread:
    """Writes a board's stream to a PtyDevice in real time (for the `tecdard imu` tests and the bench)."""

    def __init__(self, device: PtyDevice, board: Board, chunk_s: float = 0.005, mutate=None):
        self.device = device
        self.board = board
        self.chunk_s = chunk_s
        self.mutate = mutate           # optional function(bytes) -> bytes, for fault injection
        self.override = None           # optional (gyro rad/s (3,), accel m/s^2 (3,)) sent instead of rest
        self.pending: collections.deque = collections.deque()   # impacts' samples to add, (gyro, accel) rows
        self.written_t: list[float] = []  # monotonic s at which each impact's first packet was written
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="imu-emulator", daemon=True)
        self.rng = np.random.default_rng(0)

    def start(self) -> "StreamThread":
        self.thread.start()
        return self

    def impact(self, peak_m_s2: float = 30.0, ring_hz: float = 150.0, tau_s: float = 0.01,
               direction=(1.0, 0.0, 0.0), twist_rad_s: float = 0.05) -> None:
        """A knock on the held object, from the next chunk on: the fingertip's decaying ring (`peak_m_s2` at
        `ring_hz`, decaying with `tau_s`) along `direction` (IMU frame), and a short twist of the gyro."""
        t = np.arange(int(round(8 * tau_s * self.board.params.odr_hz))) / self.board.params.odr_hz
        ring = peak_m_s2 * np.exp(-t / tau_s) * np.sin(2 * np.pi * ring_hz * t)
        accel = np.outer(ring, np.asarray(direction, float))
        gyro = np.outer(twist_rad_s * np.exp(-t / tau_s), [0.0, 1.0, 0.0])
        self.pending.extend([None, *zip(gyro, accel)])      # None: the impact's first sample follows

    def _run(self) -> None:
        n = max(1, int(round(self.board.params.odr_hz * self.chunk_s)))
        t_next = time.monotonic()
        while not self.stop.is_set():
            t_next += n / self.board.params.odr_hz
            gyro = self.rng.normal(0, 0.005, (n, 3))
            accel = np.tile([0.0, 0.0, 9.81], (n, 1)) + self.rng.normal(0, 0.03, (n, 3))
            if self.override is not None:            # e.g. a chip stuck at full scale (clipped by the board)
                gyro, accel = np.tile(self.override[0], (n, 1)), np.tile(self.override[1], (n, 1))
            started, k = False, 0
            while k < n and self.pending:                  # an impact under way
                row = self.pending.popleft()
                if row is None:
                    started = True
                    continue
                gyro[k] += row[0]
                accel[k] += row[1]
                k += 1
            frames = self.board.packets(gyro, accel)
            if self.device.master is not None:
                try:        # OSError: unplugged meanwhile
                    if self.mutate is not None:
                        self.device.write(self.mutate(b"".join(frames)))
                    else:
                        self.device.write_frames(frames)
                except OSError:
                    pass
            if started:
                self.written_t.append(time.monotonic())
            delay = t_next - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)

    def join(self) -> None:
        self.stop.set()
        self.thread.join(2.0)


class PyWire:
    """`imu.source: sim-wire`: the simulated fingertip's samples encoded by the Python board onto a pty."""

    def __init__(self, board: Board, device: PtyDevice):
        self.board = board
        self.device = device

    @property
    def dropped(self) -> int:
        return self.device.dropped_frames

    def send(self, raw: np.ndarray) -> None:
        """Raw int16 samples (n, 6) as the chip made them; never blocks (frames the reader has no room for
        are dropped and counted)."""
        if self.device.master is not None:
            try:
                self.device.write_frames(self.board.packets_raw(raw))
            except OSError:
                self.device.dropped_frames += 1

    def close(self) -> None:
        self.device.close()


# the largest write a pipe takes whole or not at all (POSIX PIPE_BUF), in whole 12-byte records
ATOMIC_RECORDS = 4096 // 12


class FirmwareWire:
    """`imu.source: sim-firmware`: the firmware itself as the fingertip's board. The simulated chip's
    samples go to the host board (firmware/build/host-board) on its stdin, into the LSM6DSR register
    model, through the firmware's driver, batching, sample clock and encoder, and out on its pty."""

    def __init__(self, binary: str, link: str, odr_hz: int, gyro_fs_dps: int, accel_fs_g: int):
        self.proc = subprocess.Popen(
            [binary, "--pty", link, "--signal", "-", "--signal-fs", f"{gyro_fs_dps},{accel_fs_g}",
             "--odr", str(odr_hz), "--gyro-fs", str(gyro_fs_dps), "--accel-fs", str(accel_fs_g)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
            process_group=0)       # the terminal's Ctrl-C is the daemon's: it closes the board after the arm
        self.fd = self.proc.stdin.fileno()
        os.set_blocking(self.fd, False)
        self.dropped = 0                   # samples the host board had no room for

    def send(self, raw: np.ndarray) -> None:
        """Raw int16 samples (n, 6), each a 12-byte record; written in whole records (a pipe write of up to
        4096 bytes is all or nothing), never blocking: what the board cannot take now is dropped."""
        data = np.ascontiguousarray(raw, "<i2").tobytes()
        step = ATOMIC_RECORDS * 12
        for k in range(0, len(data), step):
            try:
                os.write(self.fd, data[k:k + step])
            except BlockingIOError:
                self.dropped += (len(data) - k) // 12
                return
            except OSError:                # the board has gone: its reader sees the port vanish
                self.dropped += (len(data) - k) // 12
                return

    def close(self) -> None:
        try:
            self.proc.stdin.close()        # the end of the signal: the board stops and removes its port
        except OSError:
            pass
        try:
            self.proc.wait(2.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
