"""Issue 48 §4: any IMU, any rate. Every condition of the trigger adapts to the IMU's rate or says in one
line why it cannot run there and runs without it; a recording at any rate from 200 Hz up is never refused
for a condition that is off; error messages name values as numbers."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from tecdard.config import Config, ConfigError
from tecdard.control.onset import OnsetDetector
from tecdard.recording.format import Recording, RecordingError, load_recording, save_recording
from tecdard.recording.replay import open_replay, run_replay
from tecdard.sim.scenarios import Scenario, generate


def _recording(tmp_path, imu_hz: float, tcp_hz: float = 125.0, **kw):
    sc = Scenario(kind="edge-arc", imu_hz=imu_hz, tcp_hz=tcp_hz, duration_s=1.0, seed=3, **kw)
    fields, truth = generate(sc)
    path = tmp_path / f"rec_{imu_hz:g}.npz"
    save_recording(path, Recording.from_fields(fields), truth)
    return path, truth


@pytest.mark.parametrize("imu_hz", [200.0, 250.0, 400.0, 1000.0])
def test_a_recording_at_any_rate_from_200_hz_is_localized(tmp_path, caplog, imu_hz):
    """A tool IMU at a few hundred Hz: the band condition is off by default, so nothing is said of it,
    the recording replays, and the arc's onset is found: dated within 30 ms of the truth (a 120 Hz click
    is beyond a 200 Hz IMU's band; the fingertip's twist then dates it)."""
    path, truth = _recording(tmp_path, imu_hz)
    with caplog.at_level(logging.WARNING, logger="tecdar"):
        r = open_replay(path)
        rows, onset_t, last = run_replay(r)
    assert not [m for m in caplog.messages if "band" in m]
    assert onset_t is not None and abs(onset_t - float(truth["onset_t"])) <= 0.03
    assert last is not None and np.isfinite(last.p).all()


def test_a_band_too_high_for_the_rate_is_lowered_or_off_with_one_line(tmp_path, caplog):
    """band_threshold on, band_hz [40, 200] with a 250 Hz IMU: the band runs on 40-112.5 Hz and the
    replay says so in one line; at 100 Hz nothing of the band fits and it is off, the others run."""
    path, _ = _recording(tmp_path, 250.0)
    cfg = tmp_path / "band.yaml"
    cfg.write_text("estimator:\n  onset:\n    band_threshold: 0.5\n")
    with caplog.at_level(logging.WARNING, logger="tecdar"):
        r = open_replay(path, str(cfg))
    said = [m for m in caplog.messages if "band" in m]
    assert len(said) == 1 and "40-112.5 Hz" in said[0] and "np.float64" not in said[0]
    assert r.pipeline.detector.band is not None
    rows, onset_t, _ = run_replay(r)
    assert onset_t is not None
    det = OnsetDetector(accel_threshold=0.4, band_threshold=0.5, odr_hz=100.0)
    assert det.band is None and "off" in det.rate_notice and "100 Hz" in det.rate_notice


def test_the_twist_window_follows_the_rate():
    det = OnsetDetector(odr_hz=6667.0, twist_threshold=0.03)
    assert det.twist_window == 33
    det.set_odr(250.0)
    assert det.twist_window == 1
    det.set_odr(1000.0)
    assert det.twist_window == 5


def test_band_hz_itself_is_still_checked():
    from tests.conftest import sim_config
    from tecdard.runtime.daemon import Daemon
    with pytest.raises(ConfigError, match=r"estimator\.onset\.band_hz: expected \[lo, hi\] with lo < hi, got \[200, 40\]"):
        Daemon(Config(sim_config(**{"estimator.onset.band_hz": [200.0, 40.0]})))


def test_errors_name_values_as_numbers(tmp_path):
    """A recording whose timestamps go backwards: the row and the two times as plain numbers."""
    path, _ = _recording(tmp_path, 1000.0)
    rec = load_recording(path)
    t = rec.imu_t.copy()
    t[10] = t[9] - 1e-4
    bad = tmp_path / "backwards.npz"
    data = dict(np.load(path, allow_pickle=False))
    data["imu_t"] = t
    np.savez(bad, **data)
    with pytest.raises(RecordingError) as err:
        load_recording(bad)
    msg = str(err.value)
    assert "np.float64" not in msg and "row 10" in msg and "s after" in msg
