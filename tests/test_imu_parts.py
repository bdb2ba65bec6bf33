"""The board's second part, the LSM6DSO/LSM6DSOX (WHO_AM_I 0x6C): the identity packet the board sends after each
status, the part's own ranges (no 4000 dps), and the part shown by `status`. The firmware's side is in
firmware/tests/test_core.c and tests/test_firmware.py."""
import numpy as np
import pytest

from tecdard.cli.show import status_lines
from tecdard.drivers import imu_wire as W
from tecdard.drivers.lsm6dsr import (ACCEL_SENS_MG_PER_LSB, GYRO_SENS_MDPS_PER_LSB, LSM6DSO, LSM6DSR, PARTS, Scaling,
                                     part_name)
from tecdard.drivers.serial_imu import SerialImuSource, SerialParams


def test_identity_packets_parse_and_count_as_good():
    stream = W.encode_status(6667, 2000, 16) + W.encode_identity(0x6C) + W.frame(W.TYPE_IDENTITY, b"\x6b\x01\x02")
    stream += W.frame(W.TYPE_IDENTITY, b"")
    parser = W.WireParser()
    pkts = parser.feed(stream)
    assert [type(p).__name__ for p in pkts] == ["StatusPacket", "IdentityPacket", "IdentityPacket"]
    assert (pkts[1].who_am_i, pkts[2].who_am_i) == (0x6C, 0x6B)     # a longer payload: its first byte
    c = parser.counters
    assert (c.good_packets, c.identity_packets, c.malformed, c.unknown_types) == (3, 2, 1, 0)
    assert W.frame_bytes(pkts[2]) == len(W.frame(W.TYPE_IDENTITY, b"\x6b\x01\x02"))


def test_the_parts_tables_are_the_datasheets():
    """DS12544 (LSM6DSR) and DS12140 Table 2 (LSM6DSO): the same sensitivity at each range both have;
    4000 dps only on the LSM6DSR."""
    assert PARTS == {0x6B: LSM6DSR, 0x6C: LSM6DSO}
    assert LSM6DSO.gyro_fs_dps == (125, 250, 500, 1000, 2000) and LSM6DSO.accel_fs_g == (2, 4, 8, 16)
    assert [GYRO_SENS_MDPS_PER_LSB[fs] for fs in LSM6DSO.gyro_fs_dps] == [4.375, 8.75, 17.5, 35.0, 70.0]
    assert [ACCEL_SENS_MG_PER_LSB[fs] for fs in LSM6DSO.accel_fs_g] == [0.061, 0.122, 0.244, 0.488]
    with pytest.raises(ValueError, match="4000 is not an LSM6DSO/LSM6DSOX range"):
        Scaling(4000, 16, LSM6DSO)
    assert Scaling(2000, 16, LSM6DSO).saturation[0] == pytest.approx(40.03, abs=0.01)   # 32767 x 70 mdps, rad/s
    assert part_name(0x6C) == "LSM6DSO/LSM6DSOX" and part_name(0x69) == "unknown (WHO_AM_I 0x69)"
    assert part_name(None) is None


def decode(src, data):
    return src.decode(data, 1.0)


def test_a_lsm6dso_board_is_named_and_held_to_its_ranges():
    src = SerialImuSource(SerialParams(port="/dev/null"))          # config: 4000 dps until the first status
    assert src.part is None
    raw = np.full((8, 6), 1000, "<i2")
    out = decode(src, W.encode_status(6667, 2000, 16) + W.encode_identity(0x6C) + W.encode_samples(0, 0, raw))
    assert src.part == "LSM6DSO/LSM6DSOX"
    assert out[1][0, 0] == pytest.approx(1000 * 70e-3 * np.pi / 180)      # scaled at 2000 dps
    events = src.drain_events()
    assert [e["code"] for e in events] == ["imu_config_range"]
    assert "no 4000 dps" in events[0]["message"] and "imu.serial.gyro_fs_dps" in events[0]["message"]
    # a status from that board claiming 4000 dps is not the part's: ignored whole, counted, said once
    decode(src, W.encode_status(6667, 4000, 16) + W.encode_samples(1, 1200, raw))
    assert src.status.gyro_fs_dps == 2000 and src.parser.counters.bad_status == 1
    assert "4000 is not an LSM6DSO/LSM6DSOX range" in src.drain_events()[0]["message"]


def test_an_unknown_sensor_is_said_once_and_a_config_that_fits_says_nothing():
    src = SerialImuSource(SerialParams(port="/dev/null", gyro_fs_dps=2000))
    decode(src, W.encode_status(6667, 2000, 16) + W.encode_identity(0x6C) + W.encode_identity(0x6C))
    assert src.drain_events() == []
    decode(src, W.encode_identity(0x69) + W.encode_identity(0x69))
    events = src.drain_events()
    assert [e["code"] for e in events] == ["imu_unknown_part"] and "0x69" in events[0]["message"]
    assert src.part == "unknown (WHO_AM_I 0x69)"


def test_status_shows_the_imus_rate_and_part():
    lines = status_lines({"mode": "idle", "imu": {"rate_hz": 6667.0, "part": "LSM6DSO/LSM6DSOX"}})
    assert any("IMU" in line and "6667 samples/s, LSM6DSO/LSM6DSOX" in line for line in lines), lines
    lines = status_lines({"mode": "idle", "imu": {"rate_hz": None, "part": None}})
    assert any("IMU" in line and "no rate yet" in line for line in lines), lines
