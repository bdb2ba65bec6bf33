"""Malformed recordings: the red team's cases and a hypothesis fuzz tier through the real reader
(tecdard.recording.load_recording) and, for what it accepts, the real replay (tecdard.localize).

Whatever the file, the reader returns a recording or raises one RecordingError line, in bounded
time and memory; a recording it accepts replays without an exception.
"""
import io
import json
import resource
import time
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tecdard.sim.scenarios import Scenario, generate
from tecdard.recording.format import MAX_DURATION_S, Recording, RecordingError, load_recording

MAX_MESSAGE_CHARS = 300
LOAD_TIME_MAX_S = 5.0           # any refusal, on this shared machine (the zip bomb took 35 s)
RSS_GROWTH_MAX_KB = 200_000     # and no allocation of what a header merely declares (the bomb took 8.9 GB)


def recording_members(with_truth: bool = False) -> dict:
    """A short valid recording's members, as savez would write them (and its truth_* with_truth)."""
    fields, truth = generate(Scenario(kind="edge-arc", seed=3, duration_s=0.3, rest_s=0.1))
    rec = Recording.from_fields(fields)
    out = {"format": np.array("tecdar-recording/1"), "imu_t": rec.imu_t, "gyro": rec.gyro, "accel": rec.accel,
           "tcp_t": rec.tcp_t, "tcp_pos": rec.tcp_pos, "tcp_quat": rec.tcp_quat,
           "imu_in_tcp_quat": rec.imu_in_tcp_quat, "meta": np.array(json.dumps({"robot": "sim"}))}
    for key in ("grip_force", "tcp_vel", "plane_normal"):
        if getattr(rec, key) is not None:
            out[key] = getattr(rec, key)
    if with_truth:
        out.update({f"truth_{k}": np.asarray(v) for k, v in truth.items()})
    return out


@pytest.fixture(scope="module")
def arrays():
    return recording_members()


def write(path, arrays, compressed=True):
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return path


def refusal(path) -> str:
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    with pytest.raises(RecordingError) as info:
        load_recording(path)
    assert time.monotonic() - t0 < LOAD_TIME_MAX_S
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < RSS_GROWTH_MAX_KB
    msg = str(info.value)
    assert "\n" not in msg and len(msg) <= MAX_MESSAGE_CHARS, msg
    return msg


def member_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=True)
    return buf.getvalue()


def raw_npz(path, members: dict, compression=zipfile.ZIP_DEFLATED):
    """An .npz from raw member bytes (so that headers and data can disagree)."""
    with zipfile.ZipFile(path, "w", compression) as zf:
        for name, data in members.items():
            zf.writestr(name + ".npy", data)
    return path


def with_changes(arrays, **changes):
    out = dict(arrays)
    for k, v in changes.items():
        if v is None:
            out.pop(k, None)
        else:
            out[k] = v
    return out


def header_declaring(shape, dtype="<f8") -> bytes:
    header = {"descr": dtype, "fortran_order": False, "shape": shape}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


# -- the red team's cases -----------------------------------------------------------------------
def test_non_utf8_text_is_refused(arrays, tmp_path):
    assert "format: not UTF-8" in refusal(write(tmp_path / "a.npz", with_changes(arrays, format=np.array(b"\xff\xfe"))))
    assert "meta: not UTF-8" in refusal(write(tmp_path / "b.npz", with_changes(arrays, meta=np.array(b"{\xff}"))))
    assert "lone surrogates" in refusal(write(tmp_path / "c.npz", with_changes(arrays, meta=np.array("\ud800"))))


@pytest.mark.parametrize("meta,fragment", [
    ("[" * 100_000 + "]" * 100_000, "nested"), ('{"a": ' + "9" * 5000 + "}", "an integer of 5000 characters"),
    ("[1, 2]", "expected a JSON object"), ('{"a": NaN}', "NaN is not a JSON number"),
])
def test_hostile_meta_is_refused(arrays, tmp_path, meta, fragment):
    assert fragment in refusal(write(tmp_path / "m.npz", with_changes(arrays, meta=np.array(meta))))


def test_a_bad_crc_and_broken_deflate_are_corrupt_data_not_pickles(arrays, tmp_path):
    path = write(tmp_path / "s.npz", arrays, compressed=False)
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("gyro.npy")
    at = info.header_offset + 30 + len(info.filename) + 200        # inside gyro's data
    data[at] ^= 0xFF
    (tmp_path / "crc.npz").write_bytes(bytes(data))
    msg = refusal(tmp_path / "crc.npz")
    assert "gyro: corrupt data" in msg and "pickled" not in msg
    path = write(tmp_path / "d.npz", arrays)
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("accel.npy")
    at = info.header_offset + 30 + len(info.filename) + info.compress_size // 2
    data[at:at + 16] = b"\x00" * 16
    (tmp_path / "deflate.npz").write_bytes(bytes(data))
    msg = refusal(tmp_path / "deflate.npz")
    assert msg.startswith("accel:") and "pickled" not in msg


def test_headers_declaring_more_than_they_hold_allocate_nothing(arrays, tmp_path):
    members = {k: member_bytes(v) for k, v in arrays.items()}
    members["gyro"] = header_declaring((10 ** 12, 3))                # 7.28 TiB declared, no data
    assert "the header declares shape (1000000000000, 3)" in refusal(raw_npz(tmp_path / "h.npz", members))
    members["gyro"] = header_declaring((len(arrays["imu_t"]), 3)) + b"\x00" * 10
    assert "gyro:" in refusal(raw_npz(tmp_path / "h2.npz", members))


def test_a_zip_bomb_is_refused_from_its_declared_size(arrays, tmp_path):
    """A member that expands to 24 GB: refused by its declared rows before anything is inflated."""
    n = 10 ** 9
    header = header_declaring((n, 3))
    path = tmp_path / "bomb.npz"
    members = {k: member_bytes(v) for k, v in arrays.items() if k != "imu_t"}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name + ".npy", data)
        with zf.open("imu_t.npy", "w", force_zip64=True) as f:     # streamed: written compressed, never held
            f.write(header_declaring((n,)))
            zeros = b"\x00" * (1 << 20)
            for _ in range(64):                                     # 64 MiB of zeros is enough to prove the point
                f.write(zeros)
    del header
    assert path.stat().st_size < 1 << 20
    assert "imu_t:" in refusal(path)


def test_time_spans_and_magnitudes_are_bounded(arrays, tmp_path):
    t = arrays["imu_t"].copy()
    t[-1] = t[0] + 1e9                                                  # two samples 1e9 s apart
    assert f"at most {MAX_DURATION_S:g} s" in refusal(write(tmp_path / "span.npz", with_changes(arrays, imu_t=t)))
    big = arrays["imu_t"] * 0 + 1e300 + np.arange(len(arrays["imu_t"])) * 1e290
    assert "imu_t: timestamps beyond" in refusal(write(tmp_path / "big.npz", with_changes(arrays, imu_t=big)))


def test_an_imu_rate_no_onset_band_fits_is_refused_by_the_reader(arrays, tmp_path):
    """Hypothesis found it: IMU times one second apart gave a 1 Hz rate, and the pipeline's onset band
    (40-200 Hz) then failed its own config check, naming a config key for a recording's fault."""
    n = len(arrays["imu_t"])
    for t, rate in ((np.arange(n) * 1.0, "1 Hz"), (np.arange(n) * 1e-6, "1e+06 Hz")):
        msg = refusal(write(tmp_path / "rate.npz", with_changes(arrays, imu_t=t)))
        assert msg.startswith("imu_t: a median sample rate of") and rate in msg, msg


def test_pickles_are_refused(arrays, tmp_path):
    members = {k: member_bytes(v) for k, v in arrays.items()}
    members["gyro"] = member_bytes(np.array([{"a": 1}] * 3, dtype=object))
    assert "gyro: holds Python objects (pickled)" in refusal(raw_npz(tmp_path / "p.npz", members))


def localize(*args):
    """`tecdard localize ARGS` in this process (the subprocess path is tests/test_localize.py's)."""
    import contextlib
    import types
    from tecdard.cli.main import main
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = main(["localize", *map(str, args)])
    return types.SimpleNamespace(returncode=code, stderr=err.getvalue(), stdout=out.getvalue())


def test_localize_refuses_bad_outputs_and_configs_with_one_line(arrays, tmp_path):
    good = write(tmp_path / "good.npz", arrays)
    for out in (tmp_path / "missing" / "est.csv", tmp_path):
        res = localize(good, "--out", out)
        assert res.returncode == 2 and res.stderr.startswith("tecdard localize: --out: cannot write"), res.stderr
        assert len(res.stderr.strip().splitlines()) == 1
    (tmp_path / "bin.yaml").write_bytes(bytes(range(256)))
    res = localize(good, "--config", tmp_path / "bin.yaml")
    assert res.returncode == 2 and "not UTF-8" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    res = localize(write(tmp_path / "nan.npz", with_changes(arrays, meta=np.array("[" * 10 ** 5))))
    assert res.returncode == 2 and "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1


# -- the fuzz tier ------------------------------------------------------------------------------
KEYS = ("format", "imu_t", "gyro", "accel", "tcp_t", "tcp_pos", "tcp_quat", "imu_in_tcp_quat", "grip_force",
        "tcp_vel", "plane_normal", "meta")
dtypes = st.sampled_from(["<f8", "<f4", "<i8", "<i2", "|u1", "|b1", "<c16", "<U8", "|S8", ">f8"])


def _cast(shape, dt, fill):
    """An array of `fill` cast to `dt` whatever it loses (NaN and inf into integers are the point)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.full(shape, fill).astype(dt, casting="unsafe")


def hostile_array(n):
    return st.one_of(
        st.builds(_cast,
                  st.lists(st.integers(0, 5), max_size=3).map(tuple), dtypes,
                  st.one_of(st.floats(allow_nan=True), st.integers(-10, 10))),
        st.builds(lambda k, v: np.full((n, k), v), st.integers(1, 5), st.floats(allow_nan=True)),
        st.builds(lambda cut: np.arange(n - cut, dtype=float), st.integers(-3, 3)),
        st.sampled_from([np.array("tecdar-recording/1"), np.array(b"tecdar-recording/1"), np.array("{}"),
                         np.array(3.0), np.zeros((0, 3)), np.array([1.0, 0, 0, 0]), np.array([0.0, 0.0, 0.0, 2.0])]),
    )


def fuzz(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def outcome(path) -> str:
    """"refused" (one short line) or "replayed" (the replay ran without an exception)."""
    from tecdard.control.geometry import quat_to_matrix
    from tecdard.config import Config
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.replay import replay
    try:
        rec = load_recording(path)
    except RecordingError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and len(msg) <= MAX_MESSAGE_CHARS, msg
        return "refused"
    pipeline = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
        plane_normal=rec.plane_normal)
    replay(rec, pipeline)
    return "replayed"


@pytest.mark.slow
@fuzz(120)
@given(st.lists(st.tuples(st.sampled_from(KEYS + ("junk",)), st.one_of(st.none(), st.integers(0, 10 ** 6))),
                min_size=1, max_size=3), st.data())
def test_any_member_swapped_for_a_hostile_array_is_refused_or_replays(arrays, tmp_path, changes, data):
    n = len(arrays["imu_t"])
    out = dict(arrays)
    for key, choice in changes:
        if choice is None:
            out.pop(key, None)
        else:
            out[key] = data.draw(hostile_array(n if key in ("imu_t", "gyro", "accel") else len(arrays["tcp_t"])))
    assert outcome(write(tmp_path / "f.npz", out)) in ("refused", "replayed")


@pytest.mark.slow
@fuzz(150)
@given(st.booleans(), st.floats(0.0, 1.0), st.binary(min_size=1, max_size=64), st.integers(0, 200))
def test_any_corrupted_archive_is_refused_or_replays(arrays, tmp_path, compressed, where, junk, cut):
    raw = bytearray(write(tmp_path / "src.npz", arrays, compressed).read_bytes())
    at = int(where * (len(raw) - 1))
    (tmp_path / "f.npz").write_bytes(bytes(raw[:at]) + junk + bytes(raw[at + cut:]))
    assert outcome(tmp_path / "f.npz") in ("refused", "replayed")


@pytest.mark.slow
@fuzz(60)
@given(st.sampled_from(["gyro", "accel", "tcp_pos", "tcp_vel", "grip_force"]),
       st.sampled_from([0.0, 1e-300, 1e3, 1e6, 1e12, 1e100, -1e100]),
       st.sampled_from(["none", "gap", "late_tcp", "two_tcp", "burst"]), st.integers(0, 2 ** 16))
def test_valid_but_extreme_recordings_replay_without_an_exception(arrays, tmp_path, key, scale, timing, seed):
    """Finite values of the right shape at any magnitude, and odd timing: the estimator must not raise."""
    rng = np.random.default_rng(seed)
    out = dict(arrays)
    m = len(arrays["tcp_t"])
    if key == "grip_force":
        out[key] = np.full(m, abs(scale))
    else:
        base = out.get(key, np.zeros((m, 3)))
        out[key] = base + scale * rng.standard_normal(base.shape)
    t, tt = arrays["imu_t"].copy(), arrays["tcp_t"].copy()
    if timing == "gap":
        t[len(t) // 2:] += 1000.0                          # a 1000 s hole in the IMU stream
        tt[len(tt) // 2:] += 1000.0
    elif timing == "late_tcp":
        tt = tt + 0.25                                     # proprioception starts after most samples
    elif timing == "two_tcp":
        for k in ("tcp_pos", "tcp_quat", "tcp_vel", "grip_force"):
            if k in out:
                out[k] = out[k][:2]
        tt = tt[:2]
    elif timing == "burst":
        t = t[0] + np.cumsum(np.where(rng.random(len(t)) < 0.01, 0.05, 1.5e-4))
    out["imu_t"], out["tcp_t"] = t, tt
    assert outcome(write(tmp_path / "x.npz", out)) in ("refused", "replayed")


def test_a_written_recording_deflates_only_the_members_that_pay_and_reads_back_whole(tmp_path):
    """Issue 37: the IMU's float noise deflates to about 95 % of its size and inflating it was a
    tenth of `localize`; those members are stored, the rest deflated, and every reader (ours,
    np.load) reads the same arrays. A path without .npz gets it, as np.savez does."""
    from tecdard.recording.format import save_recording
    rec = Recording.from_fields(generate(Scenario(kind="edge-arc", seed=3, duration_s=1.0))[0])
    save_recording(tmp_path / "rec", rec, truth={"angle": np.zeros(5000)})
    path = tmp_path / "rec.npz"
    how = {i.filename: i.compress_type for i in zipfile.ZipFile(path).infolist()}
    assert how["gyro.npy"] == how["accel.npy"] == zipfile.ZIP_STORED
    assert how["truth_angle.npy"] == how["meta.npy"] == zipfile.ZIP_DEFLATED
    back = load_recording(path)
    for key in ("imu_t", "gyro", "accel", "tcp_t", "tcp_pos", "tcp_quat"):
        np.testing.assert_array_equal(getattr(back, key), getattr(rec, key))
    with np.load(path) as npz:
        np.testing.assert_array_equal(npz["gyro"], rec.gyro)
        assert json.loads(str(npz["meta"])) == rec.meta
    save_recording(tmp_path / "plain.npz", rec, compress=False)
    assert {i.compress_type for i in zipfile.ZipFile(tmp_path / "plain.npz").infolist()} == {zipfile.ZIP_STORED}
