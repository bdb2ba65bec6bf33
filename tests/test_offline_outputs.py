"""The offline tools' inputs and outputs (issue 32, items 7, 12 and 13): an output that is the input
is refused, a failed write leaves what was there, an image is written where it was asked, and
every member of a recording (live_events, truth_*) is read as strictly as the rest.

A fuzz tier sends hostile live_events and truth members through localize, plot and export: each
refuses with one line (exit 2) or works; none tracebacks, none takes unbounded memory or time."""
import io
import json
import os
import resource
import signal
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tecdard.recording.format import load_recording
from tests.conftest import ROOT, tecdard
from tests.test_fuzz_recordings import recording_members

HAS_FOXGLOVE = __import__("importlib").util.find_spec("foxglove") is not None
HAS_MATPLOTLIB = __import__("importlib").util.find_spec("matplotlib") is not None
ONE_LINE_CHARS = 400


@pytest.fixture(scope="module")
def arrays():
    return recording_members(with_truth=True)


def live_keys(arrays, events) -> dict:
    """A daemon recording's live_* keys around `arrays` (one pass), with `events` as live_events."""
    n_imu, n_tcp = len(arrays["imu_t"]), len(arrays["tcp_t"])
    return {"live_pass_end": np.array([n_imu], np.int64), "live_tcp_pass": np.zeros(n_tcp, np.int64),
            "live_tcp_w": np.zeros((n_tcp, 3)), "live_changes": np.array(json.dumps([])),
            "live_bias0": np.zeros(4), "live_est": np.zeros((0, 7)),
            "live_events": np.array(events if isinstance(events, str) else json.dumps(events))}


def one_line_refusal(res, command: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    err = res.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1 and len(err) <= ONE_LINE_CHARS, err
    assert err.startswith(f"tecdard {command}: "), err
    return err


# -- outputs ------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.skipif(not HAS_MATPLOTLIB, reason="the viz extra (matplotlib) is installed by `make test`")
def test_a_plot_without_a_contact_has_no_empty_panels_and_no_warning(tmp_path):
    """Issue 50 item 15: a capture at rest (no onset) drew four empty panels (the turn, the estimate's
    three) and matplotlib warned of legends with nothing in them. Now: the signals' three panels, the
    title says no contact, and no warning; a recording with a contact and its truth keeps all eight."""
    from PIL import Image
    contact = tmp_path / "contact.npz"
    assert tecdard("sim-record", contact).returncode == 0
    with np.load(contact) as z:
        rest = {k: z[k] for k in z.files if not k.startswith("truth_")}
    rng = np.random.default_rng(0)
    n = len(rest["imu_t"])
    rest["gyro"] = 0.002 * rng.standard_normal((n, 3))
    rest["accel"] = np.array([0.0, 0.0, -9.81]) + 0.01 * rng.standard_normal((n, 3))
    rest["tcp_pos"] = np.repeat(rest["tcp_pos"][:1], len(rest["tcp_t"]), axis=0)
    rest["tcp_quat"] = np.repeat(rest["tcp_quat"][:1], len(rest["tcp_t"]), axis=0)
    if "tcp_vel" in rest:
        rest["tcp_vel"] = np.zeros_like(rest["tcp_vel"])
    np.savez_compressed(tmp_path / "rest.npz", **rest)
    heights = {}
    for name in ("rest", "contact"):
        res = subprocess.run([sys.executable, "-W", "error::UserWarning", "-m", "tecdard", "plot",
                              str(tmp_path / f"{name}.npz"), "-o", str(tmp_path / f"{name}.png")],
                             capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert res.returncode == 0 and "Warning" not in res.stderr, res.stderr
        heights[name] = Image.open(tmp_path / f"{name}.png").size[1]
        assert ("no contact detected" in res.stdout) == (name == "rest"), res.stdout
    # 1.9 in a panel at 100 dpi: four panels' height (the least drawn) against eight (with the error's)
    assert heights == {"rest": 760, "contact": 1520}, heights


@pytest.mark.slow
def test_an_output_that_is_the_input_is_refused_and_the_recording_kept(arrays, tmp_path):
    rec = tmp_path / "REC.npz"
    np.savez_compressed(rec, **arrays)
    before = rec.read_bytes()
    link = tmp_path / "same.npz"
    os.symlink(rec, link)
    runs = [("localize", "--out", rec), ("localize", "--out", link)]
    if HAS_FOXGLOVE:
        runs += [("export", "--mcap", rec), ("export", "--mcap", link)]
    if HAS_MATPLOTLIB:
        runs += [("plot", "-o", rec)]
    for command, option, out in runs:
        err = one_line_refusal(tecdard(command, rec, option, out), command)
        assert "is the input" in err, err
        assert rec.read_bytes() == before


@pytest.mark.slow
@pytest.mark.skipif(not HAS_FOXGLOVE, reason="the viz extra (foxglove-sdk) is installed by `make test`")
def test_a_failed_export_leaves_the_good_mcap_it_would_have_replaced(arrays, tmp_path):
    rec = tmp_path / "REC.npz"
    np.savez_compressed(rec, **arrays)
    good = tmp_path / "good.mcap"
    assert tecdard("export", rec, "--mcap", good).returncode == 0
    before = good.read_bytes()

    def small_files():             # RLIMIT_FSIZE: a write past 64 kB fails (EFBIG), as a full disk would
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64_000, 64_000))
    res = subprocess.run([sys.executable, "-m", "tecdard", "export", str(rec), "--mcap", str(good)],
                         capture_output=True, text=True, timeout=120, cwd=ROOT, preexec_fn=small_files)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("tecdard export: --mcap: "), res.stderr
    assert good.read_bytes() == before
    assert [f for f in os.listdir(tmp_path) if f.startswith(".partial-")] == []
    # a device that cannot take it: one line, and nothing created beside it
    res = tecdard("export", rec, "--mcap", "/dev/full")
    assert res.returncode == 2 and "No space left" in res.stderr.strip().splitlines()[-1], res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.slow
@pytest.mark.skipif(not HAS_MATPLOTLIB, reason="the viz extra (matplotlib) is installed by `make test`")
def test_plot_writes_where_it_was_asked_and_never_beside_a_device(arrays, tmp_path):
    rec = tmp_path / "REC.npz"
    np.savez_compressed(rec, **arrays)
    res = tecdard("plot", rec, "-o", tmp_path / "NAME")
    assert res.returncode == 0 and res.stdout.startswith(f"{tmp_path / 'NAME'}: "), res.stderr
    assert (tmp_path / "NAME").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "NAME.png").exists()
    res = tecdard("plot", rec, "-o", tmp_path / "p.svg")
    assert res.returncode == 0 and (tmp_path / "p.svg").read_text().lstrip().startswith("<?xml")
    err = one_line_refusal(tecdard("plot", rec, "-o", tmp_path / "p.nonsense"), "plot")
    assert "no image format for .nonsense" in err
    existed = os.path.exists("/dev/full.png")
    err = one_line_refusal(tecdard("plot", rec, "-o", "/dev/full"), "plot")
    assert "No space left" in err and os.path.exists("/dev/full.png") == existed


# -- inputs: live_events and truth_* ----------------------------------------------------------------

HOSTILE_EVENTS = {
    "items that are not objects": ([1, "x", None], "live_events[0]: expected a JSON object"),
    "a t of 1e300": ([{"t": 1e300, "kind": "fault"}], "live_events[0].t: 1e+300 is no time"),
    "a t of 1e12": ([{"t": 1e12, "kind": "fault"}], "live_events[0].t: 1000000000000.0 is no time"),
    "a t that is a string": ([{"t": "0", "kind": "fault"}], "live_events[0].t:"),
    "a kind that is a number": ([{"t": 0.1, "kind": 3}], "live_events[0].kind: expected a string"),
    "not a list": ({"kind": "fault"}, "live_events: expected a JSON list"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(HOSTILE_EVENTS))
def test_hostile_live_events_are_one_line_refusals_in_every_tool(arrays, tmp_path, case):
    events, said = HOSTILE_EVENTS[case]
    path = tmp_path / "hostile.npz"
    np.savez_compressed(path, **arrays, **live_keys(arrays, events))
    tools = [("localize",)] + ([("export", "--mcap", tmp_path / "o.mcap")] if HAS_FOXGLOVE else []) \
        + ([("plot", "-o", tmp_path / "o.png")] if HAS_MATPLOTLIB else [])
    for command, *rest in tools:
        err = one_line_refusal(tecdard(command, path, *rest), command)
        assert said in err, (command, err)


def bomb_member(zf: zipfile.ZipFile, name: str, n: int) -> None:
    """A member declaring n float64 zeros, streamed compressed (never held)."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (n,)})
    with zf.open(name + ".npy", "w", force_zip64=True) as f:
        f.write(header.getvalue())
        zeros = b"\x00" * (1 << 20)
        for _ in range(n * 8 >> 20):
            f.write(zeros)


@pytest.mark.slow
def test_a_truth_member_is_read_through_the_bounded_reader(arrays, tmp_path):
    """A 1.6 MB file with a truth member of 1.2 GB took 1.2 GB and 21 s in plot and export."""
    from tecdard.recording.format import RecordingError, load_truth
    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, **{k: v for k, v in arrays.items() if not k.startswith("truth_")})
    with zipfile.ZipFile(path, "a", zipfile.ZIP_DEFLATED) as zf:
        bomb_member(zf, "truth_p_c", 32 << 20)           # 256 MiB declared, a few hundred kB on disk
    # (the format's bound for a truth member is a series as long as the IMU's may be: 96 MB)
    assert path.stat().st_size < 2 << 20
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    with pytest.raises(RecordingError, match="truth_p_c: 268435456 bytes declared"):
        load_truth(path)
    assert time.monotonic() - t0 < 2.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 50_000
    for command, *rest in ([("export", "--mcap", tmp_path / "o.mcap")] if HAS_FOXGLOVE else []) \
            + ([("plot", "-o", tmp_path / "o.png")] if HAS_MATPLOTLIB else []):
        t0 = time.monotonic()
        err = one_line_refusal(tecdard(command, path, *rest), command)
        assert "truth_p_c" in err and time.monotonic() - t0 < 60.0


# -- the fuzz tier --------------------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10 ** 20, 10 ** 20) | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=8)
events_strategy = st.lists(st.one_of(
    json_values,
    st.fixed_dictionaries({"t": st.one_of(st.floats(allow_nan=False), st.integers(-10 ** 15, 10 ** 15), json_values),
                           "kind": st.one_of(st.sampled_from(["fault", "contact_onset", "task_done"]), json_values)},
                          optional={"task": json_values, "result": json_values})), max_size=5)


@pytest.mark.slow
@settings(max_examples=60, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(events=events_strategy)
def test_any_live_events_load_or_are_one_line_refusals(arrays, tmp_path, events):
    """Through the reader every tool shares: load_live returns the events, each a dict with a string
    kind and a finite t near the recording, or raises one RecordingError line."""
    from tecdard.recording.format import RecordingError
    from tecdard.recording.live import load_live
    path = tmp_path / "fuzz.npz"
    np.savez(path, **arrays, **live_keys(arrays, events))
    rec = load_recording(path)
    try:
        live = load_live(path, rec)
    except RecordingError as exc:
        assert "\n" not in str(exc) and len(str(exc)) <= ONE_LINE_CHARS
        return
    for ev in live.events:
        assert isinstance(ev, dict) and isinstance(ev["kind"], str) and np.isfinite(ev["t"])
        assert abs(ev["t"] - rec.imu_t[0]) <= 2 * 3600.0


def _ticks(arrays, n_joints: int = 6) -> np.ndarray:
    t = np.arange(arrays["imu_t"][0], arrays["imu_t"][-1], 0.02)
    return np.column_stack([t, np.full((len(t), n_joints), 0.01)])


@pytest.mark.parametrize("name, cmd, said", [
    ("joint rates of a 3-D block", lambda a: _ticks(a)[None], "live_cmd: expected shape (T, 1 + 1..12 joints)"),
    ("a time alone", lambda a: _ticks(a)[:, :1], "live_cmd: expected shape (T, 1 + 1..12 joints)"),
    ("times that go back", lambda a: _ticks(a)[::-1], "live_cmd: tick times must increase strictly"),
    ("ticks an hour after the samples", lambda a: _ticks(a) + np.r_[3600.0, np.zeros(6)], "live_cmd: tick times must"),
    ("a rate of 1000 rad/s", lambda a: _ticks(a) + np.r_[0.0, 1000.0, np.zeros(5)], "beyond 100 rad/s"),
    ("a NaN rate", lambda a: _ticks(a) + np.r_[np.zeros(6), np.nan], "live_cmd: contains NaN or inf"),
])
def test_a_bad_live_cmd_is_a_one_line_refusal_naming_it(arrays, tmp_path, name, cmd, said):
    """Issue 52: the control ticks' commands (a dataset's action) are read as strictly as every member."""
    from tecdard.recording.format import RecordingError
    from tecdard.recording.live import load_live
    path = tmp_path / "cmd.npz"
    np.savez(path, **arrays, **live_keys(arrays, []), live_cmd=cmd(arrays))
    with pytest.raises(RecordingError) as err:
        load_live(path, load_recording(path))
    assert said in str(err.value) and "\n" not in str(err.value), (name, str(err.value))


def test_joint_rates_without_their_joints_are_refused(arrays, tmp_path):
    from tecdard.recording.format import RecordingError
    from tecdard.recording.live import load_live
    path = tmp_path / "qd.npz"
    np.savez(path, **arrays, **live_keys(arrays, []), live_qd=np.zeros((len(arrays["tcp_t"]), 6)))
    with pytest.raises(RecordingError, match="live_qd: the joints' rates without live_q"):
        load_live(path, load_recording(path))


def test_a_live_cmd_loads_as_the_ticks_and_their_joint_rates(arrays, tmp_path):
    from tecdard.recording.live import load_live
    path = tmp_path / "cmd.npz"
    np.savez(path, **arrays, **live_keys(arrays, []), live_cmd=_ticks(arrays))
    live = load_live(path, load_recording(path))
    np.testing.assert_array_equal(live.cmd, _ticks(arrays))


@settings(max_examples=40, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(value=st.one_of(
    st.builds(lambda shape, dt: np.zeros(shape, dt), st.lists(st.integers(0, 40), max_size=3).map(tuple),
              st.sampled_from(["<f8", "<i4", "|u1", "<U4", "|b1", "<c16", "|S3"])),
    st.sampled_from([np.array("edge"), np.array([np.nan, np.inf, 0.0]), np.zeros(10_000)])))
def test_any_truth_member_loads_bounded_or_is_a_one_line_refusal(arrays, tmp_path, value):
    from tecdard.recording.format import MAX_TRUTH_BYTES, RecordingError, load_truth
    path = tmp_path / "t.npz"
    np.savez(path, **{k: v for k, v in arrays.items() if not k.startswith("truth_")}, truth_p_c=value)
    try:
        truth = load_truth(path)
    except RecordingError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("truth_p_c: ")
        return
    assert truth["p_c"].nbytes <= MAX_TRUTH_BYTES
