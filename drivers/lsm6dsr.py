"""ST LSM6DSR and LSM6DSO/LSM6DSOX: full-scale settings and sensitivities (datasheets), raw int16 -> SI."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# LSM6DSR (DS12544 Table 2): the union of both parts' ranges; the LSM6DSO has the same sensitivities
# at every range it has (DS12140 Table 2) and no 4000 dps
GYRO_SENS_MDPS_PER_LSB = {125: 4.375, 250: 8.75, 500: 17.5, 1000: 35.0, 2000: 70.0, 4000: 140.0}
ACCEL_SENS_MG_PER_LSB = {2: 0.061, 4: 0.122, 8: 0.244, 16: 0.488}


@dataclass(frozen=True)
class Part:
    """A sensor the board may carry, known by the WHO_AM_I it reports in its identity packet."""
    name: str
    who_am_i: int
    gyro_fs_dps: tuple[int, ...]
    accel_fs_g: tuple[int, ...]
    datasheet: str


LSM6DSR = Part("LSM6DSR", 0x6B, (125, 250, 500, 1000, 2000, 4000), (2, 4, 8, 16), "ST DS12544")
# one WHO_AM_I for the LSM6DSO and the LSM6DSOX (their register maps agree where the board uses them); the
# LSM6DSO32 answers 0x6C too, but its accelerometer's ranges are 4-32 g: not a part the board supports
LSM6DSO = Part("LSM6DSO/LSM6DSOX", 0x6C, (125, 250, 500, 1000, 2000), (2, 4, 8, 16), "ST DS12140, DS13158")
PARTS = {p.who_am_i: p for p in (LSM6DSR, LSM6DSO)}


def part_name(who_am_i: int | None) -> str | None:
    """The part a WHO_AM_I names, or what else answered (None: the board has not said)."""
    if who_am_i is None:
        return None
    part = PARTS.get(who_am_i)
    return part.name if part is not None else f"unknown (WHO_AM_I {who_am_i:#04x})"
STANDARD_GRAVITY_M_S2 = 9.80665
DEFAULT_ODR_HZ = 6667
# The chip's output data rates (datasheet Table 52/53, high-performance mode), Hz; a board reports
# the one configured, rounded (12.5 Hz as 12 or 13).
ODR_HZ = (12.5, 26.0, 52.0, 104.0, 208.0, 416.0, 833.0, 1666.0, 3332.0, 6667.0)
ODR_TOL = 0.05                 # a reported rate within this fraction of one of ODR_HZ is that rate
RAW_MAX = 32767
DEFAULT_GYRO_FS_DPS = 4000
DEFAULT_ACCEL_FS_G = 16


def odr_problem(odr_hz: float) -> str | None:
    """Why a reported output data rate is none of the chip's, or None."""
    if any(abs(odr_hz - r) <= ODR_TOL * r for r in ODR_HZ):
        return None
    return f"odr_hz {odr_hz:g} is not an LSM6DSR rate ({', '.join(f'{r:g}' for r in ODR_HZ)} Hz)"


class Scaling:
    """Raw (n, 6) int16 [gx, gy, gz, ax, ay, az] to SI (rad/s, m/s^2) at the given full scales, checked
    against `part`'s ranges (the LSM6DSR's by default: the widest)."""

    def __init__(self, gyro_fs_dps: int = DEFAULT_GYRO_FS_DPS, accel_fs_g: int = DEFAULT_ACCEL_FS_G,
                 part: Part = LSM6DSR):
        self.part = part
        self.set(gyro_fs_dps, accel_fs_g)

    def set(self, gyro_fs_dps: int, accel_fs_g: int) -> None:
        if gyro_fs_dps not in self.part.gyro_fs_dps:
            raise ValueError(f"gyro_fs_dps: {gyro_fs_dps} is not an {self.part.name} range "
                             f"({', '.join(map(str, self.part.gyro_fs_dps))})")
        if accel_fs_g not in self.part.accel_fs_g:
            raise ValueError(f"accel_fs_g: {accel_fs_g} is not an {self.part.name} range "
                             f"({', '.join(map(str, self.part.accel_fs_g))})")
        self.gyro_fs_dps = gyro_fs_dps
        self.accel_fs_g = accel_fs_g
        self.gyro_rad_s_per_lsb = GYRO_SENS_MDPS_PER_LSB[gyro_fs_dps] * 1e-3 * math.pi / 180.0
        self.accel_m_s2_per_lsb = ACCEL_SENS_MG_PER_LSB[accel_fs_g] * 1e-3 * STANDARD_GRAVITY_M_S2

    @property
    def saturation(self) -> tuple[float, float]:
        """(gyro rad/s, accel m/s^2): a sample this large on any axis is clipped at full scale
        (int16 +32767 or -32768; half an LSB below, so that rounding on the way to SI is no issue)."""
        return ((RAW_MAX - 0.5) * self.gyro_rad_s_per_lsb, (RAW_MAX - 0.5) * self.accel_m_s2_per_lsb)

    def to_si(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raw = raw.astype(np.float64)
        return raw[:, 0:3] * self.gyro_rad_s_per_lsb, raw[:, 3:6] * self.accel_m_s2_per_lsb

    def to_raw(self, gyro: np.ndarray, accel: np.ndarray) -> np.ndarray:
        """SI to int16 (rounded, saturated): what the chip would report."""
        g = np.round(gyro / self.gyro_rad_s_per_lsb)
        a = np.round(accel / self.accel_m_s2_per_lsb)
        return np.clip(np.hstack([g, a]), -32768, 32767).astype("<i2")
