"""Issue 48 §3: the trigger and the estimator on what a real rig does to the signal (sim/rig.py, sim/profiles.py),
on shorter runs than benchmarks/robustness.py's 30 minutes. Every disturbance at its nominal level (1x):
no onset in free motion, acceleration steps with 125 Hz states 8 ms late among them; a trigger that
re-arms on the vibrating arm; an impact dated within 5 ms and decided at its ring's reversal; an
impact-free rotation dated within 30 ms; the 180 ms error within 1.5x of its clean value and covered
by 3 sigma. At 3x: never a confident wrong answer."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.robustness import false_onsets, impact, rotation
from tecdard.control.onset import OnsetDetector
from tecdard.control.onset_guard import Predictor
from tecdard.recording import replay as L
from tecdard.recording.format import Recording
from tecdard.sim.profiles import free_motion
from tecdard.sim.rig import RigParams
from benchmarks.onset import pipeline


@pytest.mark.parametrize("profile", ["ur-cb3", "pendant"])
def test_no_onset_in_free_motion_at_1x(profile):
    """UR trapezoids and a pendant jog (steps up to 1.5 m/s^2 and 3 rad/s^2, states at 125 Hz 8 ms late)
    with the sensor's errors, the arm's vibration, the clocks and a 5 deg mount error."""
    onsets, minutes, kinds = false_onsets(profile, 1.0, "", 0.5, seed=11)
    assert minutes > 0.3 and onsets == 0, kinds


def test_acceleration_steps_with_late_states_do_not_fire():
    """The check the issue keeps: a clean board on an arm that starts with acceleration steps and whose
    states come at 125 Hz, 8 ms late. Before, the trigger fired at the arm's start."""
    onsets, minutes, kinds = false_onsets("ur-cb3", 1.0, "latency", 0.5, seed=12)
    assert onsets == 0, kinds
    fields, _ = free_motion("ur-cb3", 30.0, rig=RigParams().at(1.0, "latency"), seed=12)
    rec = Recording.from_fields(fields)
    pipe = pipeline(rec)
    L.replay_onsets(rec, pipe)
    assert pipe.detector.guard.explained_steps > 0          # steps were seen, and the arm's states explained them


def test_the_trigger_re_arms_on_a_vibrating_arm():
    """Fired on an impact, released: the rest levels are the vibrating arm's, so it settles within
    a second while the arm keeps vibrating, and a second impact fires again."""
    rng = np.random.default_rng(3)
    odr = 6667.0
    det = OnsetDetector(accel_threshold=0.4, odr_hz=odr, settle_s=0.25)
    det.floor.k = 4.0

    def vibrating(t0: float, n: int):
        t = t0 + np.arange(n) / odr
        a = np.column_stack([0.5 * np.sin(2 * np.pi * 40.0 * t + k) for k in range(3)]) + rng.normal(0, 0.03, (n, 3))
        return t, a + [0.0, 0.0, 9.81]

    t0, fired, hits = 0.0, [], []
    for k in range(60):                        # 6 s of 100 ms batches
        t, a = vibrating(t0, 667)
        if k in (20, 45):
            a[300:330] += [4.0, 0.0, 0.0]      # an impact
            hits.append(float(t[300]))
        hit = det.process(t, a)
        if hit >= 0:
            fired.append(float(t[hit]))
            det.rearm(settle=True)
        t0 = float(t[-1]) + 1.0 / odr
    assert len(fired) == 2 and np.allclose(fired, hits, atol=0.001), (fired, hits)
    assert not det.settling and det.armed
    # the paper's fixed 0.4 m/s^2 against an idle board's rest would never have settled here
    assert det.accel_threshold_now() > 1.0


def test_a_task_start_settles_on_a_dithering_arm():
    """The daemon re-arms with settling at every task start. The servo's dither (sim.rig: 0.015 rad/s RMS
    about 40 Hz) turns the fingertip to and fro across the twist's threshold over its 5 ms mean; the
    still that ends settling is judged on the twist's 50 ms hold mean, so the trigger arms (before, it
    never did on the daemon's simulated arm at 1x, and the approach found no table)."""
    rng = np.random.default_rng(4)
    odr = 6667.0
    det = OnsetDetector(accel_threshold=0.4, odr_hz=odr, settle_s=0.25, twist_threshold=0.03)
    t0 = 0.0
    for k in range(30):                        # 3 s of 100 ms batches
        t = t0 + np.arange(667) / odr
        gyro = np.column_stack([0.02 * np.sin(2 * np.pi * 40.0 * t + j) for j in range(3)]) \
            + rng.normal(0, 0.005, (667, 3))
        accel = rng.normal(0, 0.03, (667, 3)) + [0.0, 0.0, 9.81]
        assert det.process(t, accel, gyro) < 0
        if k == 5:
            det.rearm(settle=True)
        t0 = float(t[-1]) + 1.0 / odr
    assert det.armed and not det.settling


def _narrow_band(rng, n: int, odr: float, hz: float = 40.0, rms: float = 0.4) -> np.ndarray:
    """(n, 3) m/s^2: a lightly damped mode about `hz` driven by white noise (sim/rig.py's servo dither)."""
    w = 2 * np.pi * hz
    r = np.exp(-0.15 * w / odr)
    pole = r * np.exp(1j * w / odr)
    drive = (rng.normal(0, 1, (n, 3)) + 1j * rng.normal(0, 1, (n, 3))) * rms * np.sqrt(1 - r * r)
    y = np.zeros((n, 3), dtype=complex)
    state = np.zeros(3, dtype=complex)
    for i in range(n):
        state = pole * state + drive[i]
        y[i] = state
    return y.real


@pytest.mark.parametrize("horizon_s", [0.001, 0.0])
def test_an_impact_under_the_arms_narrow_band_vibration(horizon_s):
    """A 40 Hz servo dither at 0.4 m/s^2 RMS per axis, and a 1.5 m/s^2 impact 4 ms long: predicted from
    its own past, the dither is taken off and the impact fires within 2 ms, with nothing in
    6 s of dither before it. Judged on the remainder itself, the moving floor (4 x 0.7 m/s^2) hides it.
    (sim/rig.py's dither is more predictable: there the floor stays under the paper's 0.4.)"""
    rng = np.random.default_rng(5)
    odr = 6667.0
    det = OnsetDetector(accel_threshold=0.4, odr_hz=odr)
    det.floor.k = 4.0
    det.predictor = Predictor(horizon_s, odr)
    n = int(7 * odr)
    t = np.arange(n) / odr
    a = _narrow_band(rng, n, odr) + rng.normal(0, 0.02, (n, 3)) + [0.0, 0.0, 9.81]
    k0 = int(6.5 * odr)
    pulse = 1.5 * np.sin(np.pi * np.arange(int(0.004 * odr)) / int(0.004 * odr))
    a[k0:k0 + len(pulse), 0] += pulse
    fired, thr_before = [], None
    for i in range(0, n, 67):                  # the board's 10 ms batches
        if i <= k0 < i + 67:
            thr_before = det.accel_threshold_now()
        hit = det.process(t[i:i + 67], a[i:i + 67])
        if hit >= 0:
            fired.append(float(t[i + hit]))
            det.rearm(settle=True)
    if horizon_s:
        assert len(fired) == 1 and 0.0 <= fired[0] - t[k0] <= 0.002, (fired, t[k0])
        assert thr_before < 1.2           # what the past does not predict of the dither: a third of it
    else:
        assert fired == [] and thr_before > 2.0


def test_an_impact_and_a_rotation_are_dated_on_time_at_1x():
    for seed in (1, 2):
        imp = impact(1.0, seed=seed)
        assert abs(imp["dated_ms"]) <= 5.0, imp
        # found by the accelerometer, not by the twist's 0.2 s hold (the dither is predicted away), and
        # decided at its ring's reversal (half a period, 4.2 ms), not after the arm's states (125 Hz,
        # 8 ms late: 35 ms)
        assert imp["trigger"] == "accel" and imp["detected_ms"] <= 8.0, imp
    seeds = range(1, 7)
    clean = [rotation(0.0, seed=s) for s in seeds]
    rough = [rotation(1.0, seed=s) for s in seeds]
    assert all(0.0 <= r["dated_ms"] <= 30.0 for r in rough), [r["dated_ms"] for r in rough]
    err_clean = float(np.median([r["180"][0] for r in clean]))
    err = float(np.median([r["180"][0] for r in rough]))
    covered = sum(r["180"][1] for r in rough)
    assert err <= 1.5 * err_clean and covered >= 0.9 * len(rough), (err, err_clean, covered)


@pytest.mark.slow
def test_at_3x_fewer_onsets_and_never_a_confident_wrong_answer():
    """Three times every disturbance: the impact's click is under the vibration's floor, and the
    rotation is found late; what is reported is covered by its 3 sigma."""
    rot = rotation(3.0, seed=1)
    for at in ("180", "end"):
        err, covered = rot[at]
        assert err != err or covered, (at, rot)
    onsets, minutes, kinds = false_onsets("ur-e", 3.0, "", 0.5, seed=13)
    assert onsets <= 2, kinds


@pytest.mark.parametrize("imu_hz", [1000.0, 250.0])
def test_a_slow_tool_imu_finds_the_contacts(imu_hz):
    imp = impact(1.0, imu_hz=imu_hz, seed=1)
    rot = rotation(1.0, imu_hz=imu_hz, seed=1)
    assert abs(imp["dated_ms"]) <= 5.0 + 1e3 / imu_hz, imp
    if imu_hz >= 1000.0:                                  # 250 Hz: 4 ms samples miss a 2 ms ring, the twist finds it
        assert imp["trigger"] == "accel" and imp["detected_ms"] <= 10.0, imp
    assert 0.0 <= rot["dated_ms"] <= 30.0, rot
