"""Recordings and `tecdard localize`, exactly as ../shared/specs/recording-format.md says."""
import json
import subprocess
import sys

import numpy as np
import pytest

from tecdard.sim.scenarios import Scenario, generate
from tecdard.recording.format import FORMAT, Recording, RecordingError, load_recording, load_truth, save_recording
from tests.conftest import ROOT

LOCALIZE_TOL_M = 3e-3


def scenario_file(path, **kw):
    fields, truth = generate(Scenario(**kw))
    rec = Recording.from_fields(fields)
    save_recording(path, rec, truth)
    return path


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return scenario_file(tmp_path_factory.mktemp("rec") / "arc.npz", kind="edge-arc", seed=5, duration_s=0.6)


def localize_subprocess(*args, cwd=ROOT):
    """`tecdard localize ARGS` as a user runs it."""
    return subprocess.run([sys.executable, "-m", "tecdard", "localize", *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=cwd)


def localize(*args):
    """`tecdard localize ARGS` in this process: the same entry point, without 3 s of interpreter and
    compiled-code start-up per call (localize_subprocess checks the real command line)."""
    import contextlib
    import io
    import types
    from tecdard.cli.main import main
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = main(["localize", *map(str, args)])
    return types.SimpleNamespace(returncode=code, stderr=err.getvalue(), stdout=out.getvalue())


def in_plane_error(p, truth):
    d = np.asarray(p) - truth["p_c"]
    a = truth["axis"]
    return float(np.linalg.norm(d - np.dot(d, a) * a))


def test_localize_writes_causal_rows_and_a_summary(good, tmp_path):
    out = tmp_path / "est.csv"
    res = localize_subprocess(good, "--out", out, "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert set(summary) == {"onset_t", "p_c", "std", "method"} and summary["method"] == "ekf"
    truth = load_truth(good)
    assert in_plane_error(summary["p_c"], truth) < LOCALIZE_TOL_M
    assert abs(summary["onset_t"] - float(truth["onset_t"])) < 0.005
    lines = out.read_text().splitlines()
    assert lines[0] == "t,px,py,pz,sx,sy,sz"
    rows = np.array([[float(x) for x in ln.split(",")] for ln in lines[1:]])
    assert rows[0, 0] >= summary["onset_t"]                         # rows start at onset
    assert np.all(np.diff(rows[:, 0]) > 0)
    span = rows[-1, 0] - rows[0, 0]
    assert len(rows) <= 1000 * span + 2                              # at most --rate rows per second
    assert np.all(rows[:, 4:] > 0)


def test_localize_rows_are_causal(good, tmp_path):
    """Truncating the recording after t must not change any row at or before t."""
    full = tmp_path / "full.csv"
    assert localize(good, "--out", full).returncode == 0
    rec = load_recording(good)
    cut_t = rec.imu_t[0] + 0.75
    keep_i, keep_m = rec.imu_t <= cut_t, rec.tcp_t <= cut_t
    short = Recording(rec.imu_t[keep_i], rec.gyro[keep_i], rec.accel[keep_i], rec.tcp_t[keep_m],
                      rec.tcp_pos[keep_m], rec.tcp_quat[keep_m], rec.imu_in_tcp_quat, rec.grip_force[keep_m],
                      rec.plane_normal, rec.tcp_vel[keep_m], rec.meta)
    save_recording(tmp_path / "short.npz", short)
    part = tmp_path / "part.csv"
    assert localize(tmp_path / "short.npz", "--out", part).returncode == 0
    a = np.loadtxt(full, delimiter=",", skiprows=1)
    b = np.loadtxt(part, delimiter=",", skiprows=1)
    n = len(b) - 1          # the last row of the short run may sit at the cut
    assert n > 10
    assert np.allclose(a[:n], b[:n], atol=1e-6)


@pytest.mark.parametrize("method", ["paper-ekf", "svd-geo", "gd-geo", "svd-diff", "gd-diff"])
def test_localize_methods(good, method):
    res = localize(good, "--method", method, "--json")
    assert res.returncode == 0, res.stderr
    s = json.loads(res.stdout)
    assert s["method"] == method
    assert in_plane_error(s["p_c"], load_truth(good)) < 0.02


def test_localize_3d_point_contact(tmp_path):
    path = scenario_file(tmp_path / "pen.npz", kind="point-circle", seed=2, duration_s=2.0, speed=0.03)
    res = localize(path, "--json")
    assert res.returncode == 0, res.stderr
    s = json.loads(res.stdout)
    assert np.linalg.norm(np.array(s["p_c"]) - load_truth(path)["p_c"]) < 0.01


def test_no_contact_exits_1(tmp_path):
    path = scenario_file(tmp_path / "quiet.npz", kind="edge-arc", seed=1, speed=0.02, ring_gain=0.0, duration_s=0.3)
    rec = load_recording(path)
    rec.gyro[:] = rec.gyro[:1]          # nothing happens at all: the arm at rest, the fingertip still
    rec.accel[:] = rec.accel[:1]
    rec.tcp_pos[:] = rec.tcp_pos[:1]
    rec.tcp_quat[:] = rec.tcp_quat[:1]
    if rec.tcp_vel is not None:
        rec.tcp_vel[:] = 0.0
    save_recording(path, rec)
    res = localize(path, "--json")
    assert res.returncode == 1
    assert "no contact detected" in res.stderr


def test_bad_arguments_exit_2(good):
    assert localize(good, "--method", "magic").returncode == 2
    assert localize(good, "--rate", "0").returncode == 2


# -- malformed recordings: one test per case, each a one-line error naming the key ---------------

def mutate(tmp_path, good, **changes):
    with np.load(good, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    return path


def _with(good, key, fn):
    with np.load(good, allow_pickle=False) as data:
        return fn(np.array(data[key]))


def nan_at(a, i=7):
    a = a.astype(float)
    a.flat[i] = np.nan
    return a


CASES = [
    ("format missing", lambda g: {"format": None}, "format: missing required key"),
    ("format wrong", lambda g: {"format": np.array("tecdar-recording/2")}, "format: expected"),
    ("imu_t missing", lambda g: {"imu_t": None}, "imu_t: missing required key"),
    ("gyro NaN", lambda g: {"gyro": _with(g, "gyro", nan_at)}, "gyro: contains NaN or inf"),
    ("accel inf", lambda g: {"accel": _with(g, "accel", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5, np.inf, a))}, "accel: contains NaN or inf"),
    ("tcp_pos NaN", lambda g: {"tcp_pos": _with(g, "tcp_pos", nan_at)}, "tcp_pos: contains NaN or inf"),
    # finite but no rig's reading: their sums overflowed inside the estimator
    ("accel 1e300", lambda g: {"accel": _with(g, "accel", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5, 1e300, a))}, "accel: 1e+300 at row 1 is beyond 1570"),
    ("gyro huge", lambda g: {"gyro": _with(g, "gyro", lambda a: a - 1e30)}, "gyro: -1e+30 at row 0 is beyond 700"),
    ("tcp_pos 1 km", lambda g: {"tcp_pos": _with(g, "tcp_pos", lambda a: a + [1e3, 0, 0])}, "tcp_pos: 1000"),
    ("gyro shape", lambda g: {"gyro": _with(g, "gyro", lambda a: a[:, :2])}, "gyro: expected shape (n, 3)"),
    ("gyro length", lambda g: {"gyro": _with(g, "gyro", lambda a: a[:-1])}, "gyro: has"),
    ("tcp_quat length", lambda g: {"tcp_quat": _with(g, "tcp_quat", lambda a: a[1:])}, "tcp_quat: has"),
    ("non-unit quaternion", lambda g: {"tcp_quat": _with(g, "tcp_quat", lambda a: a * np.where(np.arange(len(a))[:, None] == 3, 1.01, 1.0))}, "tcp_quat: row 3 is not a unit quaternion"),
    ("mount not unit", lambda g: {"imu_in_tcp_quat": np.array([0, 0, 0, 2.0])}, "imu_in_tcp_quat: is not a unit quaternion"),
    ("imu_t backwards", lambda g: {"imu_t": _with(g, "imu_t", lambda a: np.concatenate([a[:10], a[9:10] - 1e-4, a[11:]]))}, "imu_t: timestamps must be strictly increasing"),
    ("tcp_t repeated", lambda g: {"tcp_t": _with(g, "tcp_t", lambda a: np.concatenate([a[:4], a[3:4], a[5:]]))}, "tcp_t: timestamps must be strictly increasing"),
    ("string array", lambda g: {"tcp_t": np.array(["a", "b"])}, "tcp_t: expected a numeric array"),
    ("plane_normal not unit", lambda g: {"plane_normal": np.array([0, 2.0, 0])}, "plane_normal: expected a unit vector"),
    ("grip_force length", lambda g: {"grip_force": np.ones(3)}, "grip_force: has 3 rows"),
    ("meta not JSON", lambda g: {"meta": np.array("{oops")}, "meta: not valid JSON"),
]


@pytest.mark.parametrize("name,change,message", CASES, ids=[c[0] for c in CASES])
def test_malformed_recordings_are_rejected_by_name(tmp_path, good, name, change, message):
    path = mutate(tmp_path, good, **change(good))
    with pytest.raises(RecordingError) as info:
        load_recording(path)
    assert message in str(info.value)
    assert "\n" not in str(info.value)
    res = localize(path)
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1 and message in res.stderr


def test_not_an_npz_and_missing_file(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    for path, msg in ((junk, "not a NumPy .npz file"), (tmp_path / "none.npz", "no such file")):
        res = localize(path)
        assert res.returncode == 2 and msg in res.stderr


def test_truth_and_unknown_keys_are_ignored(tmp_path, good):
    path = mutate(tmp_path, good, truth_p_c=np.array([9.0, 9.0, 9.0]), future_key=np.arange(3))
    rec = load_recording(path)
    assert rec.imu_t.size > 0
    assert load_recording(good).imu_t.size == rec.imu_t.size


def test_minimal_recording_round_trip(tmp_path):
    """A recording with only the required keys, written as any rig would (int timestamps are fine too)."""
    n, m = 100, 5
    path = tmp_path / "min.npz"
    np.savez(path, format=np.array(FORMAT), imu_t=np.arange(n) / 6667.0, gyro=np.zeros((n, 3)),
             accel=np.tile([0, 0, 9.81], (n, 1)), tcp_t=np.arange(m) / 65.0, tcp_pos=np.zeros((m, 3)),
             tcp_quat=np.tile([0, 0, 0, 1.0], (m, 1)), imu_in_tcp_quat=np.array([0, 0, 0, 1.0]))
    rec = load_recording(path)
    assert rec.grip_force is None and rec.tcp_vel is None and rec.plane_normal is None
    assert rec.imu_rate_hz == pytest.approx(6667.0)


@pytest.mark.slow
def test_sim_record_cli(tmp_path):
    out = tmp_path / "hinge.npz"
    res = subprocess.run([sys.executable, "-m", "tecdard", "sim-record", str(out), "--kind", "hinge",
                          "--radius", "0.2", "--grip-force", "40", "--imu-in-tcp-quat", "0,0,0.7071068,0.7071068",
                          "--tool-tilt-deg", "20", "--tcp-hz", "100", "--seed", "9"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    rec, truth = load_recording(out), load_truth(out)
    assert rec.tcp_rate_hz == pytest.approx(100.0, rel=0.01)
    assert float(truth["radius"]) == 0.2 and rec.grip_force[0] == 40.0
    assert np.allclose(rec.imu_in_tcp_quat, [0, 0, 0.7071068, 0.7071068], atol=1e-6)
    bad = subprocess.run([sys.executable, "-m", "tecdard", "sim-record", str(out), "--kind", "wobble"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert bad.returncode == 2


def test_the_csv_rows_are_the_documented_format_byte_for_byte():
    """write_csv formats a row at a time with one %-format (issue 53: writing the rows cost more than
    the replay); every value is written as the per-value format said, -0, nan and inf included."""
    import io
    from tecdard.tools.localize import write_csv
    rows = np.random.default_rng(5).normal(size=(500, 7))
    rows[0, 1], rows[1, 2], rows[2, 3], rows[3, 0] = -0.0, np.nan, np.inf, 1e12
    got = io.StringIO()
    write_csv(got, rows)
    want = "t,px,py,pz,sx,sy,sz\n" + "".join(
        f"{r[0]:.9f},{r[1]:.6f},{r[2]:.6f},{r[3]:.6f},{r[4]:.6f},{r[5]:.6f},{r[6]:.6f}\n" for r in rows)
    assert got.getvalue() == want
