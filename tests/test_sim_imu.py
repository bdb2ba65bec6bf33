"""The simulated fingertip IMU: bias, noise density, quantisation, lag, eta, impact rings, the wire stream."""
import math
import time

import numpy as np
import pytest

from tecdard.sim.board import Board, BoardParams, PtyDevice, PyWire
from tecdard.drivers.lsm6dsr import Scaling
from tecdard.drivers.serial_imu import SerialImuSource, SerialParams
from tecdard.sim.imu import ETA_TRUE_TABLE, FingertipSignal, SimImu, SimImuParams

ODR = 6667.0
R_DOWN = np.diag([1.0, -1.0, -1.0])        # tool pointing down


def at_rest(sig, n):
    ts = np.arange(n) / ODR
    z = np.zeros((n, 3))
    return sig.sample(ts, z, z, z, R_DOWN)


def test_noise_density_bias_and_quantisation():
    p = SimImuParams(gyro_bias_walk=0.0)
    sig = FingertipSignal(p, seed=3)
    bias = sig.gyro_bias.copy()
    raw, g, a = at_rest(sig, 40000)
    sigma_expected = p.gyro_noise_density * math.sqrt(ODR / 2)
    lsb = Scaling(p.gyro_fs_dps, p.accel_fs_g).gyro_rad_s_per_lsb
    sigma_q = math.sqrt(sigma_expected ** 2 + lsb ** 2 / 12)          # quantisation adds LSB^2/12
    assert np.std(g, axis=0) == pytest.approx([sigma_q] * 3, rel=0.05)
    assert np.allclose(g.mean(axis=0), R_DOWN.T @ np.zeros(3) + bias, atol=3 * sigma_q / math.sqrt(40000) + lsb)
    assert np.allclose(g / lsb, np.round(g / lsb), atol=1e-9)           # every value is a whole LSB
    assert raw.dtype == np.dtype("<i2")
    assert np.mean(a[:, 2]) == pytest.approx(-9.81 + sig.accel_bias[2], abs=0.02)   # gravity, sensor z down


def test_bias_drifts_as_a_random_walk():
    p = SimImuParams(gyro_bias_walk=1e-3, gyro_noise_density=0.0)
    ends = []
    for seed in range(30):
        sig = FingertipSignal(p, seed=seed)
        b0 = sig.gyro_bias.copy()
        at_rest(sig, int(ODR))             # one second
        ends.append(sig.gyro_bias - b0)
    assert np.std(np.array(ends)) == pytest.approx(1e-3, rel=0.3)      # sigma * sqrt(1 s)


def test_lag_step_response_and_eta():
    p = SimImuParams(gyro_noise_density=0.0, gyro_bias_max=0.0, gyro_bias_walk=0.0, lag_tau_s=0.004,
                     grip_force_n=20.0, gyro_fs_dps=125)
    sig = FingertipSignal(p, seed=0)
    n = int(0.05 * ODR)
    ts = np.arange(n) / ODR
    w_obj = np.tile([0.0, 0.5, 0.0], (n, 1))
    _, g, _ = sig.sample(ts, np.zeros((n, 3)), w_obj, np.zeros((n, 3)), np.eye(3))
    eta = dict(ETA_TRUE_TABLE)[20.0]
    final = 0.5 / eta
    k_tau = int(round(0.004 * ODR))
    assert g[k_tau, 1] == pytest.approx(final * (1 - math.exp(-(k_tau + 1) / (0.004 * ODR))), rel=0.03)
    assert g[-1, 1] == pytest.approx(final, rel=0.01)


def test_gripper_rotation_is_seen_in_full():
    p = SimImuParams(gyro_noise_density=0.0, gyro_bias_max=0.0, gyro_bias_walk=0.0, gyro_fs_dps=125)
    sig = FingertipSignal(p, seed=0)
    n = 2000
    w = np.tile([0.0, 0.0, 0.3], (n, 1))
    _, g, _ = sig.sample(np.arange(n) / ODR, w, w, np.zeros((n, 3)), np.eye(3))   # object turns with the gripper
    assert g[-1, 2] == pytest.approx(0.3, abs=Scaling(125, 16).gyro_rad_s_per_lsb)


def test_impact_ring_scales_with_speed_and_mass():
    def peak(speed, mass):
        p = SimImuParams(accel_noise_density=0.0, accel_bias_max=0.0, object_mass_kg=mass, accel_fs_g=2)
        sig = FingertipSignal(p, seed=0)
        sig.impact(0.0, np.array([1.0, 0, 0]), speed)
        n = int(0.05 * ODR)
        _, _, a = sig.sample(np.arange(n) / ODR, *(np.zeros((n, 3)),) * 3, np.eye(3))
        return np.max(np.abs(a[:, 0]))
    assert peak(0.02, 0.1) == pytest.approx(2 * peak(0.01, 0.1), rel=0.05)
    # 4x the mass: half the amplitude, and half the frequency, so the first peak comes later on
    # the same decay envelope (tau 15 ms): peaks at 1/(4 f)
    envelope = math.exp(-(1 / (4 * 60.0) - 1 / (4 * 120.0)) / 0.015)
    assert peak(0.02, 0.4) == pytest.approx(0.5 * envelope * peak(0.02, 0.1), rel=0.05)


def test_wire_stream_round_trips_through_the_serial_driver(tmp_path):
    dev = PtyDevice(tmp_path / "ttyIMU")
    board = Board(BoardParams())
    imu = SimImu(SimImuParams(), seed=1, wire=PyWire(board, dev))
    src = SerialImuSource(SerialParams(port=str(dev.link)))
    src.open()
    try:
        t = np.linspace(0.0, 0.5, 501)
        z = np.zeros((501, 3))
        w = np.tile([0.0, 0.2, 0.0], (501, 1))
        Rs = np.tile(np.eye(3), (501, 1, 1))
        expected = []
        orig = imu.signal.sample

        def spy(*a, **k):
            out = orig(*a, **k)
            expected.append(out[1])
            return out
        imu.signal.sample = spy
        got = []
        for k in range(0, 500, 50):                 # 50 ms slices, read as they arrive
            imu.feed(t[k:k + 51], z[k:k + 51], w[k:k + 51], z[k:k + 51], Rs[k:k + 51])
            n_want = sum(len(e) for e in expected)
            t_end = time.monotonic() + 10
            while sum(len(x[0]) for x in got) < n_want and time.monotonic() < t_end:
                out = src.read(0.05)
                if out is not None:
                    got.append(out)
        want = np.vstack(expected)
        gyro = np.vstack([x[1] for x in got])
        assert len(gyro) == len(want)
        assert np.allclose(gyro, want, atol=1e-12)          # bit-exact through the wire
        assert src.counters()["crc_errors"] == 0 and src.status.odr_hz == 6667
        assert dev.dropped_frames == 0
    finally:
        src.close()
        dev.close()
