"""`tecdar-imu/1` parsing, scaling and clock mapping: pure logic, fuzzed."""
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from tecdard.drivers import imu_wire as W
from tecdard.sim.board import Board, BoardParams
from tecdard.drivers.lsm6dsr import ACCEL_SENS_MG_PER_LSB, GYRO_SENS_MDPS_PER_LSB, Scaling
from tecdard.drivers.serial_imu import SerialImuSource, SerialParams
from tecdard.drivers.timesync import ClockSync, Unwrapper

# Golden packets; CRCs computed by hand with a bit-by-bit CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF).
GOLDEN_STATUS = bytes.fromhex("a55a 02 0600 0b1a a00f 10 00 bc1a".replace(" ", ""))
GOLDEN_SAMPLES = bytes.fromhex("a55a 01 1300 0100 40420f00 01 6400 9cff 0000 0000 0000 0108 9d75".replace(" ", ""))
SAMPLE_TIME_TOL_S = 0.5e-3


def test_crc_check_value():
    assert W.crc16(b"123456789") == 0x29B1


def test_golden_packets_decode_and_encode():
    p = W.WireParser()
    pkts = p.feed(GOLDEN_STATUS + GOLDEN_SAMPLES)
    assert pkts[0] == W.StatusPacket(6667, 4000, 16, 0)
    s = pkts[1]
    assert (s.seq, s.t0_us) == (1, 1_000_000)
    assert s.raw.tolist() == [[100, -100, 0, 0, 0, 2049]]
    assert W.encode_status(6667, 4000, 16) == GOLDEN_STATUS
    assert W.encode_samples(1, 1_000_000, np.array([[100, -100, 0, 0, 0, 2049]])) == GOLDEN_SAMPLES
    c = p.counters
    assert (c.good_packets, c.samples, c.status_packets, c.bytes_discarded) == (2, 1, 1, 0)


def stream(n_packets=20, n=8, seq0=0):
    rng = np.random.default_rng(0)
    return [W.encode_samples(seq0 + k, 1000 * k, rng.integers(-3000, 3000, (n, 6))) for k in range(n_packets)]


def parse_all(data: bytes, chunk: int = 7):
    p = W.WireParser()
    out = []
    for k in range(0, len(data), chunk):
        out += p.feed(data[k:k + chunk])
    return p, out


@pytest.mark.parametrize("chunk", [1, 3, 64, 10000])
def test_split_anywhere(chunk):
    pk = stream()
    p, out = parse_all(b"".join(pk), chunk)
    assert [o.seq for o in out] == list(range(20))
    assert p.counters.bytes_discarded == 0


def test_garbage_between_packets_is_discarded_and_counted():
    pk = stream(5)
    data = b"\x00\x11\xa5" + pk[0] + b"junk\xa5\xa5" + pk[1] + pk[2] + b"\x5a" * 9 + pk[3] + pk[4]
    p, out = parse_all(data)
    assert [o.seq for o in out] == [0, 1, 2, 3, 4]
    assert p.counters.bytes_discarded == 3 + 6 + 9


def test_crc_error_loses_only_that_packet():
    pk = stream(4)
    bad = bytearray(pk[1])
    bad[12] ^= 0xFF
    p, out = parse_all(pk[0] + bytes(bad) + pk[2] + pk[3])
    assert [o.seq for o in out] == [0, 2, 3]
    assert p.counters.crc_errors == 1
    assert p.counters.samples_lost == 8          # seq 1 missing, 8 samples per packet


def test_long_len_resyncs_without_losing_the_next_packet():
    pk = stream(3)
    bad = bytearray(pk[1])
    bad[3:5] = struct.pack("<H", 2000)            # len over 1024
    p, out = parse_all(pk[0] + bytes(bad) + pk[2])
    assert [o.seq for o in out] == [0, 2]
    assert p.counters.malformed == 1


def test_corrupted_len_within_bounds_still_finds_the_following_packets():
    pk = stream(6)
    bad = bytearray(pk[1])
    bad[3:5] = struct.pack("<H", 900)             # plausible but wrong: swallows what follows until CRC fails
    data = pk[0] + bytes(bad) + b"".join(pk[2:]) + b"\x00" * 1000
    p, out = parse_all(data, 50)
    assert [o.seq for o in out] == [0, 2, 3, 4, 5]


def test_truncated_packet_then_good_one():
    pk = stream(3)
    p, out = parse_all(pk[0] + pk[1][:15] + pk[2])
    assert [o.seq for o in out] == [0, 2]


def test_unknown_type_is_skipped_by_len_and_counted():
    pk = stream(2)
    unknown = W.frame(0x7E, b"\x01\x02\x03\x04")
    p, out = parse_all(pk[0] + unknown + pk[1])
    assert [o.seq for o in out] == [0, 1]
    assert p.counters.unknown_types == 1 and p.counters.bytes_discarded == 0


def test_malformed_samples_len_and_status_len():
    good = stream(2)
    wrong_n = W.frame(W.TYPE_SAMPLES, struct.pack("<HIB", 1, 0, 3) + b"\x00" * 12 * 2)   # n=3 but 2 samples
    zero_n = W.frame(W.TYPE_SAMPLES, struct.pack("<HIB", 1, 0, 0))
    bad_status = W.frame(W.TYPE_STATUS, b"\x00" * 5)
    p, out = parse_all(good[0] + wrong_n + zero_n + bad_status + good[1])
    assert [o.seq for o in out] == [0, 1]
    assert p.counters.malformed == 3


def test_seq_wrap_and_gaps():
    rng = np.random.default_rng(1)
    pk = [W.encode_samples(s, 0, rng.integers(-5, 5, (4, 6))) for s in (65534, 65535, 0, 3)]
    p, out = parse_all(b"".join(pk))
    assert [o.seq for o in out] == [65534, 65535, 0, 3]
    assert p.counters.samples_lost == 2 * 4


def test_status_flags_count_fifo_overruns():
    p, _ = parse_all(W.encode_status(6667, 4000, 16, W.FLAG_FIFO_OVERRUN) + W.encode_status(6667, 4000, 16, 0))
    assert p.counters.fifo_overruns == 1 and p.counters.status_packets == 2


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=3000), st.integers(1, 200))
def test_fuzz_arbitrary_bytes_never_raise_and_bytes_add_up(data, chunk):
    p, out = parse_all(data, chunk)
    c = p.counters
    assert c.bytes_in == len(data)
    assert c.bytes_discarded + c.bytes_consumed + p.pending() == c.bytes_in
    assert c.samples == sum(len(o.raw) for o in out if isinstance(o, W.SamplesPacket))


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 4000), st.integers(0, 255)), max_size=6), st.integers(1, 97))
def test_fuzz_mutated_valid_streams(mutations, chunk):
    """Random byte flips in a valid stream: never raises, and every untouched packet after the first
    touched one's end is still decoded (resync never loses a good packet)."""
    pk = stream(30, n=4)
    data = bytearray(b"".join(pk))
    touched = set()
    bounds = np.cumsum([0] + [len(x) for x in pk])
    for pos, val in mutations:
        pos = pos % len(data)
        if data[pos] != val:
            data[pos] = val
            touched.add(int(np.searchsorted(bounds, pos, side="right") - 1))
    p, out = parse_all(bytes(data), chunk)
    c = p.counters
    assert c.bytes_discarded + c.bytes_consumed + p.pending() == c.bytes_in
    seqs = {o.seq for o in out if isinstance(o, W.SamplesPacket)}
    # a corrupted len can swallow at most MAX_LEN bytes after a touched packet; beyond that, all good
    lost_ok = set()
    for k in touched:
        end = bounds[k] + W.HEADER_BYTES + W.MAX_LEN + W.CRC_BYTES
        lost_ok |= {j for j in range(len(pk)) if bounds[j] < end}
    for j in range(len(pk)):
        if j not in touched and j not in lost_ok:
            assert j in seqs


@pytest.mark.parametrize("gfs", sorted(GYRO_SENS_MDPS_PER_LSB))
@pytest.mark.parametrize("afs", sorted(ACCEL_SENS_MG_PER_LSB))
def test_scaling_for_every_full_scale(gfs, afs):
    s = Scaling(gfs, afs)
    raw = np.array([[1000, -1000, 0, 1000, -1000, 0]], dtype="<i2")
    g, a = s.to_si(raw)
    assert g[0, 0] == pytest.approx(1000 * GYRO_SENS_MDPS_PER_LSB[gfs] * 1e-3 * math.pi / 180)
    assert a[0, 1] == pytest.approx(-1000 * ACCEL_SENS_MG_PER_LSB[afs] * 1e-3 * 9.80665)
    back = s.to_raw(g, a)
    assert np.array_equal(back, raw)


def test_status_packet_sets_the_full_scales_config_is_the_fallback():
    src = SerialImuSource(SerialParams(port="unused", gyro_fs_dps=2000, accel_fs_g=8))
    raw = np.array([[1000, 0, 0, 1000, 0, 0]])
    t, g, a = src.decode(W.encode_samples(0, 0, raw), 1.0)
    assert g[0, 0] == pytest.approx(1000 * 70e-3 * math.pi / 180)           # config: 2000 dps
    t, g, a = src.decode(W.encode_status(6667, 250, 2) + W.encode_samples(1, 150, raw), 1.0)
    assert g[0, 0] == pytest.approx(1000 * 8.75e-3 * math.pi / 180)          # status: 250 dps
    assert a[0, 0] == pytest.approx(1000 * 0.061e-3 * 9.80665)


def test_unknown_full_scale_is_refused():
    with pytest.raises(ValueError, match="gyro_fs_dps: 3000"):
        Scaling(3000, 16)


def test_unwrap_t0_us():
    u = Unwrapper()
    ts = [u(x) for x in (2**32 - 2000, 2**32 - 500, 700, 5000)]
    assert np.all(np.diff(ts) > 0)
    assert ts[2] - ts[1] == pytest.approx(1200e-6)


@pytest.mark.slow
def test_clock_sync_tracks_100ppm_drift_for_an_hour():
    """An hour of packets, MCU clock 100 ppm fast, random USB latency: sample times within 0.5 ms.
    Every fourth packet reaches the fit (the others as if lost on the bus): a quarter of the run time."""
    rng = np.random.default_rng(3)
    board = Board(BoardParams(drift_ppm=100.0, t0_us=2**32 - 5_000_000))   # wraps after 5 s
    odr, n = 6667, 8
    sync, unwrap = ClockSync(), Unwrapper()
    host0 = 1234.5
    worst = 0.0
    period = n / odr
    for k in range(0, int(3600 / period), 4):
        idx = k * n
        t_true = idx / odr                                     # true time of the first sample
        mcu = unwrap(board.mcu_us(idx)) + (n - 1) / (odr * (1 + 0))
        arrival = host0 + t_true + (n - 1) / odr + 0.0002 + rng.exponential(0.0005)
        sync.add(mcu, arrival)
        if k % 996 == 0 and k > 2000:
            err = float(sync.to_host(unwrap(board.mcu_us(idx)))) - (host0 + t_true)
            worst = max(worst, abs(err))
    assert worst < SAMPLE_TIME_TOL_S
    assert sync.resets == 0


@pytest.mark.parametrize("backlog_s", [0.2, 0.7])
@pytest.mark.parametrize("drift_ppm", [0.0, 100.0, -100.0])
def test_clock_sync_is_not_misled_by_a_backlog_read_at_start(backlog_s, drift_ppm):
    """The board streamed before the driver read it (the port opened, then a gripper's activation held the
    daemon's start): the first reads take `backlog_s` of packets from the kernel's buffer at once, each
    arriving long after it was sampled, and the first half-second bins' minima lie far above the envelope.
    The fit is the arrivals' lower envelope (Moon, Skelly and Towsley's linear program), so those bins never
    tilt it: sample times within SAMPLE_TIME_TOL_S of the truth from 2 s on. Before, the least-squares line
    through the bins' minima took the backlog for a clock running 3.4 % slow, and the mapped times fell
    35-200 ms behind their arrivals (a Robotiq rotate on the UR path diverged, or stopped on imu_stale)."""
    rng = np.random.default_rng(5)
    sync = ClockSync()
    period, host0, worst = 8 / 6667, 500.0, 0.0
    read_at = backlog_s                                         # the first read: everything buffered so far
    for k in range(int(20.0 / period)):
        t_true = k * period                                     # the packet's last sample, true (host) time
        mcu = t_true * (1.0 + drift_ppm * 1e-6)
        arrival = max(t_true, read_at) + 0.0002 + rng.exponential(0.0005)
        if t_true >= read_at:                                   # from then on, reads come as the packets do
            read_at = -1.0
        sync.add(mcu, host0 + arrival)
        if t_true > 2.0:
            worst = max(worst, abs(float(sync.to_host(mcu)) - (host0 + t_true + 0.0002)))
    assert worst < SAMPLE_TIME_TOL_S, f"{worst * 1e3:.2f} ms"
    assert abs(sync.b * (1.0 + drift_ppm * 1e-6) - 1.0) < 50e-6, sync.b


def _one_clock_two_devices(step_s: float, seconds: float, seed: int):
    """A board's packets (ClockSync) and an arm's states (SlewClock) stamped by one simulator's clock, as
    franky-sim stamps both: it loses `step_s` of the host's time at 10 s (it stalled), and every second it
    runs late by up to 70 ms for 0.3 s (a loaded host), both streams alike, each with its own transport
    jitter. Yields (device time, board's mapping error, arm's mapping error) against the truth."""
    from tecdard.drivers.timesync import SlewClock
    rng = np.random.default_rng(seed)
    sync, clock = ClockSync(), SlewClock()
    period, host0, step_at = 8 / 6667, 500.0, 10.0
    next_state = 0.0
    for k in range(int(seconds / period)):
        mcu = k * period
        lost = step_s if mcu > step_at else 0.0                  # the host's time the simulator's clock did not count
        true_host = host0 + mcu + lost
        late = 0.07 * max(0.0, 1.0 - (mcu % 1.0) / 0.3)          # the simulator behind its schedule, then caught up
        sync.add(mcu, true_host + late + 0.0002 + rng.exponential(0.0005))
        while next_state <= mcu:                                 # the arm's states at 500 Hz, from the same clock
            clock.add(next_state, true_host - (mcu - next_state) + late + 0.0002 + rng.exponential(0.0005))
            next_state += 0.002
        yield mcu, float(sync.to_host(mcu)) - (true_host + 0.0002), clock.to_host(mcu) - (true_host + 0.0002)


@pytest.mark.slow
@pytest.mark.parametrize("step_s", [0.01, 0.06])
def test_a_board_and_an_arm_on_one_simulated_clock_that_lost_time_stay_together(step_s):
    """franky-sim stamps the fingertip board's samples and the arm's states with its own clock, which runs late
    while the host is loaded and loses time when it stalls. The board's ClockSync and the arm's SlewClock follow
    the same step of the envelope after the same SLEW_WINDOW_S at the same SLEW_RATE: the two mappings stay
    within 1.5 ms of each other throughout, and reach the truth to SAMPLE_TIME_TOL_S. Before, the board's clock
    followed any step of over 2 ms after 1 s and at once while the arm's slewed: franky-sim's 10-70 ms lateness
    split them, and its rotates diverged 55-110x or put the hinge 14-18 mm off; before that, the board's never
    followed, and a rotate's IMU ran 60-90 ms early against the arm's states (the hinge 91 mm off)."""
    from tecdard.drivers.timesync import SLEW_RATE, SLEW_WINDOW_S
    settled = 10.0 + SLEW_WINDOW_S + 1.0 + step_s / SLEW_RATE
    apart = late = 0.0
    for mcu, err_board, err_arm in _one_clock_two_devices(step_s, settled + 2.0, seed=6):
        if mcu > 3.0:
            apart = max(apart, abs(err_board - err_arm))
        if mcu > settled:
            late = max(late, abs(err_board), abs(err_arm))
    assert apart < 0.0015, f"{apart * 1e3:.2f} ms apart"
    assert late < SAMPLE_TIME_TOL_S, f"{late * 1e3:.2f} ms from the truth"


def test_an_arms_states_that_arrive_a_second_late_read_stale_never_fresh():
    """Arrivals 1.2 s late from one moment on are a clock that lost time (franky-sim's after a stall beyond a
    second) or states that late (a controller's lag): they look the same. The board's clock restarts on a run of
    them (a board that restarted); the arm's never moves at once, so its states read 1.2 s old and the daemon
    stops on robot_stale; it is never taken ahead of the truth. An arrival a second early does restart it."""
    from tecdard.drivers.timesync import SlewClock
    errs = [(mcu, err_arm) for mcu, _, err_arm in _one_clock_two_devices(1.2, 16.0, seed=6)]
    assert max(e for mcu, e in errs if mcu > 3.0) < 0.0015
    assert all(-1.2 - 0.001 < e < -1.1 for mcu, e in errs if 10.1 < mcu < 16.0)
    clock = SlewClock()
    for k in range(2000):
        clock.add(k * 0.002, 100.0 + k * 0.002 + 0.0005 - (1.0 if k >= 1500 else 0.0))
    assert clock.resets == 1 and abs(clock.to_host(3.998) - (99.0 + 3.998 + 0.0005)) < 1e-6


def test_slew_clock_keeps_a_robots_states_in_order_through_late_and_bursty_arrivals():
    """drivers.timesync.SlewClock (the Franka link's robot clock): arrivals late by up to 60 ms
    in bursts, as a loaded host delivers a simulator's states, map to host times whose spacing
    stays within 0.2 % of the robot's own, never going back, within a millisecond or two of the
    true offset once the envelope has seen an on-time arrival."""
    from tecdard.drivers.timesync import SLEW_RATE, SLEW_WINDOW_S, SlewClock
    rng = np.random.default_rng(4)
    clock = SlewClock()
    true_offset = 1234.5
    device = np.arange(0.0, 20.0, 0.002)                       # 500 states per second
    late = rng.exponential(0.001, len(device))
    for k0 in range(0, len(device), 500):                        # every second, a 60 ms burst of lateness
        late[k0 + 100:k0 + 130] += np.linspace(0.06, 0.0, 30)
    mapped = []
    for d, lag in zip(device, late):
        clock.add(d, d + true_offset + 0.0005 + lag)
        mapped.append(clock.to_host(d))
    # from SLEW_WINDOW_S on: until then a lower envelope is taken at once (the first arrivals may be late)
    settled = device >= SLEW_WINDOW_S
    spacing = np.diff(np.array(mapped)[settled]) / np.diff(device[settled])
    assert np.all(spacing > 1.0 - SLEW_RATE - 1e-9) and np.all(spacing < 1.0 + SLEW_RATE + 1e-9)
    assert abs(mapped[-1] - (device[-1] + true_offset)) < 0.002


def test_clock_sync_spreads_a_refit_instead_of_jumping():
    """Arrivals whose lateness changes from bin to bin (a loaded host, a simulator's clock) move
    each half-second refit by milliseconds. Sample times mapped as they come keep their spacing
    within REFIT_SLEW_RATE of the board's: a refit no longer moves the mapping at once (it moved
    it back by up to 13 ms, collapsing 0.2-0.4 s of samples onto one time)."""
    from tecdard.drivers.timesync import REFIT_SLEW_RATE
    rng = np.random.default_rng(11)
    sync = ClockSync()
    period = 8 / 6667
    mapped, mcu_all = [], []
    for k in range(int(20.0 / period)):
        mcu = k * period
        lag = 0.0005 + rng.exponential(0.0005) + (0.01 if (k * period) % 1.3 < 0.6 else 0.0)
        sync.add(mcu, 100.0 + mcu + lag)
        if k > 2000:
            mapped.append(float(sync.to_host(mcu)))
            mcu_all.append(mcu)
    spacing = np.diff(mapped) / np.diff(mcu_all)
    assert np.all(np.abs(spacing - 1.0) < REFIT_SLEW_RATE + 1e-3), (spacing.min(), spacing.max())


def _source_and_packets(steps_us: dict, n_packets: int = 40, per_packet: int = 8, odr: int = 6667):
    """A serial source and n packets of a board whose clock steps back by steps_us[k] µs at packet k."""
    from tecdard.drivers.imu_wire import encode_samples, encode_status
    from tecdard.drivers.serial_imu import SerialImuSource, SerialParams
    src = SerialImuSource(SerialParams(port="/dev/null", odr_hz=odr))
    src.decode(encode_status(odr, 2000, 8), 0.0)
    frames, t_us, back = [], 60_000_000, 0
    for k in range(n_packets):
        back += steps_us.get(k, 0)
        frames.append(encode_samples(k, t_us - back, np.zeros((per_packet, 6), np.int16)))
        t_us += round(per_packet * 1e6 / odr)
    return src, frames


@pytest.mark.parametrize("step_us", [20_000, 2_000_000])
def test_a_board_clock_that_steps_back_inside_one_read_never_hands_on_times_that_go_back(step_us):
    """A 20 ms glitch or a 2 s reset of the board's clock inside one serial read: every sample's
    time is checked, the mapping re-anchors at the step (counted), the times stay increasing and
    near their arrival, never seconds in the past (which raised imu_stale while samples came)."""
    from tecdard.recording.format import _increasing
    src, frames = _source_and_packets({25: step_us})
    host = 1000.0
    out = []
    for k in range(0, 20, 5):                      # steady reads first: the fit learns the clock
        out.append(src.decode(b"".join(frames[k:k + 5]), host + k * 0.006))
    last = src.decode(b"".join(frames[20:40]), host + 0.125)          # the step is in this one read
    out.append(last)
    t = np.concatenate([o[0] for o in out])
    assert len(t) == 40 * 8                        # nothing dropped
    assert np.all(np.diff(t) > 0)
    _increasing(t, "imu_t")                        # what localize demands of a recording
    assert src.clock_steps == 1 and src.counters()["clock_steps"] == 1
    assert last[0][-1] > host + 0.125 - 0.05       # the newest sample is near its arrival, not 2 s back
    assert [e["code"] for e in src.drain_events()] == ["imu_clock_step"]
