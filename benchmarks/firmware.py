"""The fingertip board's firmware (issue 35): its size, its cost per sample, the UART's budget, the latency from a
sample's FIFO read to its packet's last byte at each batch size, and its sample times against the driver's budget;
writes benchmarks/firmware.md.

    python -m benchmarks.firmware
"""
from __future__ import annotations

import json
import os
import pathlib
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.drivers import imu_wire as W  # noqa: E402
from tecdard.drivers.serial_imu import SerialImuSource, SerialParams  # noqa: E402

OUT = ROOT / "benchmarks" / "firmware.md"
FW = ROOT / "firmware"
BUILD = FW / "build"
ODR_HZ = 6667
BATCHES = (1, 4, 8, 16, 32, 64)
SPI_HZ = 5.25e6                   # SPI1 at APB2 / 16
TARGET_HZ = 168e6
HOST_TO_M4_CYCLES = 3.0           # an x86 core retires ~3 instructions a cycle on this code, a Cortex-M4 about 1
STATUS_BYTES_S = 13               # one 13-byte status a second


def run(*args, **kw) -> str:
    return subprocess.run(list(map(str, args)), check=True, capture_output=True, text=True, **kw).stdout


def sizes() -> str:
    if not (shutil.which("arm-none-eabi-gcc")):
        return "not built here: no arm-none-eabi-gcc"
    out = run("make", "-s", "-C", FW, "cross")
    return re.search(r"flash .*", out).group(0)


def uart_rows() -> list[str]:
    rows = []
    for n in BATCHES:
        frame = 7 + 7 + 12 * n
        bps = frame / n * ODR_HZ + STATUS_BYTES_S
        rows.append(f"| {n} | {frame} | {bps / 1000:.1f} | {bps * 10 / 2e6 * 100:.0f} % | {bps * 10 / 3e6 * 100:.0f} % |")
    return rows


def latency_rows(tmp: pathlib.Path) -> list[str]:
    rows = []
    for n in BATCHES:
        c = tmp / f"lat{n}.json"
        run(BUILD / "host-board", "--out", os.devnull, "--seconds", 10, "--batch", n, "--no-self-test",
            "--poll-us", 20, "--deadline-us", 50000, "--counters", c)
        fw = json.loads(c.read_text())
        rows.append(f"| {n} | {fw['latency_mean_us'] / 1000:.2f} | {fw['latency_max_us'] / 1000:.2f} | "
                    f"{fw['packets_dropped']} |")
    return rows


def time_figures(tmp: pathlib.Path) -> tuple[float, float]:
    timing, c = tmp / "t.csv", tmp / "t.json"
    run(BUILD / "host-board", "--out", os.devnull, "--seconds", 3600, "--mcu-ppm", 80, "--mcu-wander-ppm", 20,
        "--chip-ppm", -400, "--t0-us", 2**32 - 1_000_000, "--no-self-test", "--poll-us", 500, "--timing", timing,
        "--timing-every", 4, "--counters", c)
    fw = json.loads(c.read_text())
    first, n, t0, last_ns = np.loadtxt(timing, delimiter=",", dtype=np.int64).T
    true_s = (fw["first_fifo_ns"] + first * fw["chip_period_ns"]) * 1e-9
    arrival = last_ns * 1e-9 + 0.0002 + np.random.default_rng(3).exponential(0.0005, len(first))
    out = {}
    for link in ("uart", "usb-cdc"):
        src, errs = SerialImuSource(SerialParams(port=os.devnull, link=link)), []
        rows = np.zeros((int(n[0]), 6), int)
        for k in range(len(first)):
            t = src.decode(W.encode_samples(k & 0xFFFF, int(t0[k]), rows), float(arrival[k]))[0]
            if k % 250 == 0 and k > 2000:
                errs.append(t[0] - true_s[k])
        errs = np.array(errs) * 1e3
        out[link] = (float(errs.min()), float(errs.max()))
    return out


def main() -> None:
    run("make", "-s", "-C", FW, "host")
    size = sizes()
    cost = json.loads(run(BUILD / "bench-core", 30))
    spi_us = (3 + 2 * 7 + 1) * 8 / SPI_HZ * 1e6        # a FIFO status and a two-word burst, one command byte each
    core_us = cost["p999"] * HOST_TO_M4_CYCLES / TARGET_HZ * 1e6
    with tempfile.TemporaryDirectory() as tmp:
        lat = latency_rows(pathlib.Path(tmp))
        times = time_figures(pathlib.Path(tmp))
    parts = [
        f"# The fingertip board's firmware ({time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores, {platform.python_version()})", "",
        "`python -m benchmarks.firmware` (in `make bench`) writes this page. The firmware is `firmware/` "
        "(docs/firmware.md); the host board runs its core against the LSM6DSR register model, faster than real time.",
        "", "## Size of the board image (STM32F405, `make firmware`)", "", f"- {size}; 4 kB of RAM are kept "
        "for the stack.", "",
        "## Cost per sample in the core", "",
        f"Polls that moved exactly one sample, each with its FIFO status read, burst read, pairing, stamp, batch, "
        f"and (one in 8) the encoding and CRC of a packet, on the host ({cost['polls_with_one_sample']} polls, "
        f"{cost['unit']}): median {cost['median']}, p99 {cost['p99']}, p99.9 {cost['p999']}, worst {cost['max']} "
        f"(the worst includes the host's own preemption). The register model's share is at least "
        f"{cost['model_min']}.", "",
        f"Estimate for the target (168 MHz Cortex-M4): the p99.9 at {HOST_TO_M4_CYCLES:g} M4 cycles per host cycle "
        f"is {core_us:.1f} us of CPU, and the SPI transfers at 5.25 MHz are {spi_us:.1f} us (polled): "
        f"about {core_us + spi_us:.0f} us of the 150 us between samples.", "",
        "## The UART's budget at 6667 samples/s", "",
        "Bytes a second for the samples at each batch size plus a status a second, against a UART of 10 bits a byte "
        "(the spec's 84 kB/s is the samples' 80 kB/s and their framing).", "",
        "| samples a packet | frame bytes | kB/s | share of 2 Mbaud | share of 3 Mbaud |", "|---|---|---|---|---|",
        *uart_rows(), "",
        "## Latency from a sample's FIFO read to its packet's last byte", "",
        "10 s at each batch size, the firmware polling every 20 us (the figures' resolution), the UART at 2 Mbaud, "
        "the flush deadline out of the way (50 ms): from the read of a packet's first sample to its last byte "
        "leaving the UART (the first sample waits longest). The firmware's default is 8 samples a packet with a "
        "2 ms deadline, which caps any batch at 2 ms (13 samples at 6667 Hz).", "",
        "| samples a packet | mean ms | worst ms | packets dropped |", "|---|---|---|---|", *lat, "",
        "## Sample times after the driver's clock fit", "",
        "An hour of the firmware (MCU crystal +80 ppm with a 20 ppm wander, the chip's oscillator -400 ppm, the us "
        "counter wrapping), every fourth packet fed to the serial driver at its last byte's time plus a USB "
        "latency of 0.2 ms and an exponential 0.5 ms. With `imu.serial.link: uart` (each packet dated back by "
        f"its bytes' time on the 2 Mbaud wire) mapped times are {times['uart'][0]:.2f} to {times['uart'][1]:.2f} ms "
        "after the samples' true times (budget 0.5 ms); read as a USB-CDC link (no wire time) they are "
        f"{times['usb-cdc'][0]:.2f} to {times['usb-cdc'][1]:.2f} ms after: a packet's 110 bytes take 0.55 ms on "
        "the wire, a constant the clock fit cannot tell from the board's offset.", ""]
    OUT.write_text("\n".join(parts))
    print(OUT.read_text())


if __name__ == "__main__":
    main()
