"""Onset detection: accelerometer threshold, gyro threshold, band energy, and their combinations."""
import numpy as np
import pytest

from tecdard.control.band_energy import SlidingBandEnergy
from tecdard.control.onset import OnsetDetector

ODR_HZ = 6667.0
G = np.array([0.0, 0.0, 9.81])


def quiet(n, rng, sigma=0.03):
    return G + rng.normal(0, sigma, (n, 3))


def feed(det, accel, gyro=None, chunk=50, t0=0.0):
    t = t0 + np.arange(len(accel)) / ODR_HZ
    gyro = np.zeros_like(accel) if gyro is None else gyro
    for k in range(0, len(t), chunk):
        hit = det.process(t[k:k + chunk], accel[k:k + chunk], gyro[k:k + chunk])
        if hit >= 0:
            return k + hit
    return -1


def test_accel_threshold_fires_on_the_spike_not_on_noise():
    rng = np.random.default_rng(0)
    det = OnsetDetector(accel_threshold=0.4, warmup_s=0.05)
    a = quiet(3000, rng)
    assert feed(det, a) == -1
    a2 = quiet(400, rng)
    a2[157:] += [0.0, 1.5, 0.0]
    assert feed(det, a2, t0=1.0) == 157
    assert feed(det, a2, t0=2.0) == -1          # disarmed until rearm()
    det.rearm()
    assert feed(det, a2, t0=3.0) >= 0


def test_accel_axis_ignores_other_axes():
    rng = np.random.default_rng(1)
    det = OnsetDetector(accel_threshold=0.4, accel_axis=[0, 0, 1], warmup_s=0.05)
    a = quiet(2000, rng)
    a[1000:] += [1.0, 1.0, 0.0]                 # large, but not on the probing axis
    assert feed(det, a) == -1
    a[1500:] += [0.0, 0.0, 0.8]
    det.rearm()
    assert feed(det, a, t0=1.0) == 1500


def test_gyro_threshold():
    rng = np.random.default_rng(2)
    det = OnsetDetector(accel_threshold=None, gyro_threshold=0.3, warmup_s=0.05)
    gyro = rng.normal(0, 0.005, (2000, 3)) + [0.01, 0.0, 0.0]    # with a bias
    gyro[1234:] += [0.0, 0.35, 0.0]
    assert feed(det, quiet(2000, rng), gyro) == 1234


def test_band_energy_matches_parseval():
    odr = 6400.0          # 40 Hz bins with N = 160
    band = SlidingBandEnergy(odr, 40.0, 200.0)
    t = np.arange(2000) / odr
    amp = 0.8
    x = np.zeros((2000, 3))
    x[:, 1] = amp * np.sin(2 * np.pi * 120.0 * t)
    e = np.concatenate([band.process(x[k:k + 37]) for k in range(0, 2000, 37)])
    assert e[-1] == pytest.approx(amp ** 2 / 2, rel=1e-6)
    # Out of band: a 600 Hz tone and a constant offset leave (almost) nothing.
    band2 = SlidingBandEnergy(odr, 40.0, 200.0)
    x2 = np.zeros((2000, 3))
    x2[:, 0] = 2.0 * np.sin(2 * np.pi * 600.0 * t) + 5.0
    assert band2.process(x2)[-1] < 1e-20


def test_band_energy_catches_a_heavy_object_that_the_threshold_misses():
    """A book: the ring is too small for 0.4 m/s^2 but has band energy (paper, Sec. V-C)."""
    rng = np.random.default_rng(3)
    a = quiet(4000, rng, sigma=0.02)
    t = np.arange(4000) / ODR_HZ
    on = 3000
    ring = 0.3 * np.exp(-(t[on:] - t[on]) / 0.05) * np.sin(2 * np.pi * 90 * (t[on:] - t[on]))
    a[on:, 0] += ring
    assert feed(OnsetDetector(accel_threshold=0.4, warmup_s=0.05), a) == -1
    hit = feed(OnsetDetector(accel_threshold=0.4, band_threshold=0.1, warmup_s=0.05), a)
    assert on <= hit < on + int(0.025 * ODR_HZ)


def test_all_mode_needs_every_condition_within_the_coincidence_window():
    rng = np.random.default_rng(4)
    det = OnsetDetector(accel_threshold=0.4, gyro_threshold=0.3, mode="all", coincidence_s=0.01, warmup_s=0.05)
    a, g = quiet(3000, rng), rng.normal(0, 0.005, (3000, 3))
    a[1000:1010] += [1.0, 0, 0]                  # accel alone: no
    g[2000:] += [0.0, 0.5, 0.0]                  # gyro alone, a second later: still no
    assert feed(det, a, g) == -1
    det2 = OnsetDetector(accel_threshold=0.4, gyro_threshold=0.3, mode="all", coincidence_s=0.01, warmup_s=0.05)
    a[2030:2040] += [1.0, 0, 0]                  # accel 30 samples (4.5 ms) after the gyro: yes
    assert feed(det2, a, g) == 2030


def test_detector_needs_a_condition():
    with pytest.raises(ValueError, match="enable at least one"):
        OnsetDetector(accel_threshold=None)


def test_detector_is_warm_once_it_has_seen_its_warm_up_at_rest():
    """The daemon declares itself alive only once this holds: a spike before it is not an onset."""
    rng = np.random.default_rng(1)
    det = OnsetDetector(accel_threshold=0.4, warmup_s=0.1)
    assert not det.warm
    a = quiet(400, rng)
    a[300:] += [0.0, 1.5, 0.0]                   # 45 ms in: still warming up
    assert feed(det, a) == -1 and not det.warm
    assert feed(det, quiet(400, rng), t0=1.0) == -1 and det.warm
    spike = quiet(100, rng)
    spike[20:] += [0.0, 1.5, 0.0]
    assert feed(det, spike, t0=2.0) == 20


def test_the_band_window_follows_the_source_rate():
    """Issue 17: a board at another rate than configured reports it in its status packets; the band
    energy's window (odr / band_hz[0] samples) follows, and a band that no longer fits under the new
    Nyquist rate switches that condition off with a reason instead of mistuning it."""
    det = OnsetDetector(accel_threshold=0.4, band_threshold=0.1, band_hz=(40.0, 200.0), odr_hz=ODR_HZ)
    assert det.band.N == round(ODR_HZ / 40.0)
    assert det.set_odr(ODR_HZ) is None and det.band.N == round(ODR_HZ / 40.0)
    assert det.set_odr(1666.0) is None and det.band.N == round(1666.0 / 40.0)
    problem = det.set_odr(208.0)          # issue 48: lowered under the rate's Nyquist, not switched off
    assert det.band is not None and "208 Hz" in problem and "40-93.6 Hz" in problem
    problem = det.set_odr(104.0)
    assert det.band is None and "104 Hz" in problem and "off" in problem
    assert det.set_odr(3333.0) is None and det.band.N == round(3333.0 / 40.0)


def test_the_daemon_tunes_onset_to_the_imu_source_in_use():
    """Issue 17: the onset detector took sim.imu.odr_hz even with imu.source: serial."""
    from tecdard.config import Config
    from tecdard.runtime.daemon import Daemon
    from tests.conftest import sim_config
    cfg = sim_config(**{"imu.source": "serial", "imu.serial": {"port": "/dev/null", "odr_hz": 1666},
                        "estimator.onset.band_threshold": 0.5})
    d = Daemon(Config(cfg))
    assert d.pipeline.detector.odr_hz == 1666.0 and d.pipeline.detector.band.N == round(1666 / 40.0)
    assert d.estimator.min_batch == int(1666 * d.pipeline.params.output_period_s)
    d = Daemon(Config(sim_config(**{"sim.imu.odr_hz": 3333.0})))
    assert d.pipeline.detector.odr_hz == 3333.0
