"""Live recordings (issue 20): what the daemon records replays to the live answer; `record` on demand;
the recorder's thread under a full disk, a budget and a flood."""
import errno
import importlib.util
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from tecdard.control.geometry import quat_to_matrix
from tecdard.control.pipeline import ContactEstimate, EstimatorDirective
from tecdard.control.proprio import ProprioSample
from tecdard.recording import replay as L
from tecdard.runtime import recorder as R
from tecdard.config import Config
from tecdard.control.pipeline import ContactPipeline
from tecdard.recording.format import load_recording
from tecdard.recording.live import load_live
from tecdard.runtime.capture import Pass
from tests.conftest import ROOT, DaemonProcess, daemon_config, tecdard

# the slow tier (`make check` leaves it out): whole-daemon runs that record
pytestmark = pytest.mark.slow

TASK_TIMEOUT_S = 90.0
WRITTEN_WITHIN_S = 10.0
# Replay against live: a capture starts from the live gyro bias (live_bias0), with the onset
# detector's rest statistics and the proprioception history rebuilt from its pre-onset second.
# Measured: identical to the last digit (0 over 424 estimates, after 2 s idle).
REPLAY_TOL_M = 1e-6
IDLE_BEFORE_S = 2.0


def replayed(path, config_path):
    rec = load_recording(path)
    live = load_live(path, rec)
    pipe = ContactPipeline.from_config(
        Config.load(config_path).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    rows, onset_t, last = L.replay_live(rec, live, pipe)
    return live, rows, onset_t


def rotate(d, angle_deg: float = 30.0) -> dict:
    reply = d.client.command("rotate", {"angle_deg": angle_deg})
    assert reply["ok"] is True, reply
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", ev
    written = d.client.wait_event(("recording_written",), None, WRITTEN_WITHIN_S)
    assert written["task"] == reply["task"] and written["reason"] == "the task ended"
    return written


def test_an_episode_is_recorded_and_replays_to_the_live_estimates(tmp_path):
    d = DaemonProcess(tmp_path, daemon_config(**{"record.enabled": True}))
    try:
        time.sleep(IDLE_BEFORE_S)          # the capture starts long after the estimator did
        written = rotate(d, 30.0)
    finally:
        d.close()
    live, rows, onset_t = replayed(written["path"], d.config_path)
    assert len(rows) == len(live.est) > 100
    np.testing.assert_array_equal(rows[:, 0], live.est[:, 0])      # the same outputs at the same times
    worst = float(np.max(np.linalg.norm(rows[:, 1:4] - live.est[:, 1:4], axis=1)))
    print(f"replay against live: {worst * 1e3:.5f} mm at worst over {len(rows)} estimates")
    assert worst <= REPLAY_TOL_M, f"replay {worst * 1e3:.4f} mm from live"
    onsets = [e["t"] for e in live.events if e["kind"] == "contact_onset"]
    assert onset_t == onsets[0]
    rec = load_recording(written["path"])
    # record.pre_onset_s, in whole estimator passes: the first may be a rest batch (100 ms) long
    assert 1.0 - 0.05 <= onsets[0] - rec.imu_t[0] <= 1.0 + 0.1 + 0.05
    assert rec.tcp_vel is not None and rec.meta["robot"] == "sim" and rec.meta["task"] == written["task"]
    assert rec.meta["config_digest"] and rec.meta["backend"] == "sim"
    assert {e["kind"] for e in live.events} >= {"contact_onset", "task_started", "task_done"}
    # issue 52: every control tick's command, the action a dataset learns: the tick's time, then 7 joint rates
    assert live.cmd is not None and live.cmd.shape[1] == 1 + 7, None if live.cmd is None else live.cmd.shape
    tick = np.median(np.diff(live.cmd[:, 0]))
    assert abs(tick - 0.02) < 1e-3, tick
    assert rec.imu_t[0] <= live.cmd[0, 0] and live.cmd[-1, 0] <= rec.imu_t[-1] + 0.1
    (t_start,) = [e["t"] for e in live.events if e["kind"] == "task_started"]
    moving = np.abs(live.cmd[:, 1:]).max(axis=1) > 1e-3
    assert np.all(~moving[live.cmd[:, 0] < t_start - 0.05]), "the arm was commanded before its task started"
    assert moving.sum() * tick > 1.0, f"{moving.sum()} ticks commanded a motion"
    assert live.qd is not None and live.qd.shape == (len(rec.tcp_t), 7) and np.abs(live.qd).max() > 1e-3
    assert live.axis is not None and live.axis.shape == (len(live.est), 3)
    assert abs(abs(live.axis[-1, 1]) - 1.0) < 0.05, live.axis[-1]      # the simulated cutter's hinge: along y
    if importlib.util.find_spec("pyarrow") is not None:         # the `lerobot` extra: the episode as a dataset
        ds = tmp_path / "dataset"
        res = tecdard("export", "--lerobot", ds, written["path"])
        assert res.returncode == 0, res.stderr
        import pyarrow.parquet as pq
        frames = pq.read_table(ds / "data" / "chunk-000" / "file-000.parquet").to_pydict()
        span = min(live.cmd[-1, 0], rec.tcp_t[-1], rec.imu_t[-1]) - max(live.cmd[0, 0], rec.tcp_t[0], rec.imu_t[133])
        assert abs(len(frames["index"]) - span * 50) <= 2, (len(frames["index"]), span)
        moved = np.abs(np.array(frames["action"])).max(axis=1) > 1e-3
        assert abs(moved.sum() - moving.sum()) <= 2, (moved.sum(), moving.sum())      # the ticks that moved the arm
        assert np.array(frames["observation.imu"][0]).shape == (133, 6)               # 6667 Hz / 50 fps
        assert np.array(frames["observation.contact"])[-1, 9] == 1.0                   # the hinge estimated by then
    # the command line gives the same answer
    res = tecdard("localize", written["path"], "--json", "--config", d.config_path)
    assert res.returncode == 0, res.stderr
    np.testing.assert_allclose(json.loads(res.stdout)["p_c"], rows[-1, 1:4], atol=1e-12)
    assert "leaked" not in d.log()
    if importlib.util.find_spec("matplotlib") is not None:      # the `viz` extra: a daemon recording plots
        plotted = tecdard("plot", written["path"], "-o", tmp_path / "live.png")
        assert plotted.returncode == 0 and (tmp_path / "live.png").stat().st_size > 20_000, plotted.stderr
    if importlib.util.find_spec("foxglove") is not None:        # and exports, with the live events
        topics = check_export(written["path"], tmp_path / "live.mcap")
        assert len(topics["/contact"]) == len(live.est)
        kinds = [name for name, _, _ in topics["/events"]]
        assert len(kinds) == len(live.events)
        # issue 33: wall-clock times, the arm's joints and its description, as a lab's other data has them
        times = [t for msgs in topics.values() for _, t, _ in msgs]
        assert abs(min(times) / 1e9 - time.time()) < 3600, min(times)
        assert len(topics["/joint_states"]) == len(rec.tcp_t) and live.q is not None and live.q.shape[1] == 7
        (desc,) = [json.loads(d)["data"] for _, _, d in topics["/robot_description"]]
        assert "panda_link0" in desc and "package://" not in desc
        from mcap.reader import make_reader
        with open(tmp_path / "live.mcap", "rb") as f:
            meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        assert float(meta["tecdar"]["wall_minus_monotonic_s"]) > 1e9 and meta["tecdar"]["model"] == "panda"


def test_record_on_demand_and_its_refusals(tmp_path):
    d = DaemonProcess(tmp_path, daemon_config())          # record.enabled false: captures on demand only
    try:
        c = d.client
        assert c.command("record", {"action": "stop"})["error"]["code"] == "not_recording"
        assert c.command("record", {"action": "pause"})["error"]["code"] == "bad_type"
        assert c.command("record", {})["error"]["code"] == "missing_field"
        assert c.command("record", {"action": "start", "label": "x" * 65})["error"]["code"] == "bad_type"
        assert c.command("record", {"action": "start", "extra": 1})["error"]["code"] == "unknown_field"
        started = c.command("record", {"action": "start", "label": "../bench 1"})
        assert started["ok"] is True and started["label"] == ".._bench_1"
        assert c.command("record", {"action": "start"})["error"]["code"] == "busy"
        time.sleep(1.0)
        assert c.command("record", {"action": "stop"})["ok"] is True
        written = c.wait_event(("recording_written",), None, WRITTEN_WITHIN_S)
    finally:
        d.close()
    path = written["path"]
    assert os.path.dirname(path) == str(tmp_path / "recordings") and path.endswith("-idle-.._bench_1.npz")
    assert written["reason"] == "record stop" and written["duration_s"] > 0.9
    rec = load_recording(path)
    assert rec.meta["label"] == ".._bench_1" and load_live(path, rec) is not None


def test_a_record_dir_that_cannot_be_written_is_a_config_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    cfg = daemon_config(**{"record.dir": str(blocker / "recordings")})
    path = tmp_path / "t.yaml"
    from tecdard.config import dump_yaml
    path.write_text(dump_yaml(cfg))
    res = tecdard("run", "--config", path)
    assert res.returncode == 2 and "record.dir" in res.stderr and "not writable" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


# -- the recorder's thread alone --------------------------------------------------------------

def a_pass(t0: float, n: int = 67, episode: int = 1, onset: bool = False, est: bool = False) -> Pass:
    t = t0 + np.arange(n) / 6667.0
    batch = np.column_stack([t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1))])
    proprio = [ProprioSample(t[-1], np.array([0.3, 0.0, 0.5]), np.zeros(3), np.eye(3), np.zeros(3), np.nan)]
    events = [{"kind": "contact_onset", "t": float(t[0]), "p_tcp": [0.3, 0.0, 0.5], "commanded": False}] if onset else []
    e = ContactEstimate(t=float(t[-1]), onset_t=t0, p=np.zeros(3), std=np.ones(3), cov=np.eye(3), axis=None,
                        converged=False, nis=0.0, steps=n) if est else None
    return Pass(proprio, EstimatorDirective(episode=episode), 6667.0, (80.0, 150.0), batch, events, e,
                  np.zeros(4))


def run_recorder(params, items, failing=None):
    events = []
    rec = R.Recorder(params, lambda kind, **f: events.append({"kind": kind, **f}),
                     {"robot": "sim", "imu_in_tcp_quat": [0, 0, 0, 1], "plane_normal": None})
    stop = threading.Event()
    th = threading.Thread(target=rec.run, args=(stop,))
    th.start()
    for kind, x in items:
        getattr(rec, kind)(x)
    deadline = time.monotonic() + 10.0
    while not rec._inbox.empty() and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.1)
    stop.set()
    th.join(10.0)
    assert not th.is_alive()
    return rec, events


def episode(t0: float, episode_no: int, passes: int = 40) -> list:
    """An episode: rest, an onset, estimates, then the pipeline released (a new episode number)."""
    items = [("feed", a_pass(t0 + 0.01 * k, episode=episode_no)) for k in range(20)]
    items.append(("feed", a_pass(t0 + 0.2, episode=episode_no, onset=True, est=True)))
    items += [("feed", a_pass(t0 + 0.21 + 0.01 * k, episode=episode_no, est=True)) for k in range(passes)]
    items.append(("feed", a_pass(t0 + 0.21 + 0.01 * passes, episode=episode_no + 1)))
    return items


def test_a_full_disk_is_a_counted_warning_and_the_recorder_goes_on(tmp_path, monkeypatch):
    def full(*_args, **_kw):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(R, "save_recording", full)
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1)
    rec, events = run_recorder(params, episode(100.0, 1) + episode(101.0, 2))
    failed = [e for e in events if e["kind"] == "recording_failed"]
    assert len(failed) == 2 and rec.write_failures == 2 and "No space left" in failed[0]["message"]
    assert os.listdir(tmp_path) == []                     # no partial file left behind


def test_the_budget_deletes_the_oldest_recordings_first(tmp_path, caplog):
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1, max_mb=1e-6)   # any file is over
    old = tmp_path / "20200101-000000-old.npz"
    old.write_bytes(b"x" * 1000)
    os.utime(old, (0, 0))
    with caplog.at_level("INFO", logger="tecdar.record"):
        rec, events = run_recorder(params, episode(100.0, 1) + episode(101.0, 2))
    written = [e for e in events if e["kind"] == "recording_written"]
    assert len(written) == 2
    assert sorted(os.listdir(tmp_path)) == [os.path.basename(written[-1]["path"])]     # the newest is kept
    assert sum("deleted, the oldest: the recordings are over record.max_mb" in r.message
               for r in caplog.records) == 2


def test_the_budget_never_deletes_a_file_the_daemon_did_not_write(tmp_path):
    """A user's `my-calibration-probes.npz` in record.dir was deleted by the budget (issue 32, item 4)."""
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1, max_mb=1e-6)   # any file is over
    mine = {name: tmp_path / name for name in ("my-calibration-probes.npz", "20200101-000000.npz", "notes.txt",
                                               "20200101-000000-idle.npz.bak")}
    for f in mine.values():
        f.write_bytes(b"x" * 1000)
        os.utime(f, (0, 0))
    rec, events = run_recorder(params, episode(100.0, 1) + episode(101.0, 2))
    written = [os.path.basename(e["path"]) for e in events if e["kind"] == "recording_written"]
    assert len(written) == 2
    assert sorted(os.listdir(tmp_path)) == sorted(list(mine) + written[-1:])


class Disk:
    """A filesystem of `capacity` bytes holding what is in `folder` plus `other` bytes of other files,
    as os.statvfs reports it."""

    def __init__(self, folder, capacity: int, other: int):
        self.folder, self.capacity, self.other = folder, capacity, other

    def statvfs(self, _path):
        import types
        used = self.other + sum(f.stat().st_size for f in self.folder.iterdir())
        return types.SimpleNamespace(f_bavail=max(self.capacity - used, 0), f_frsize=1, f_blocks=self.capacity)


def test_a_full_disk_loses_the_oldest_recordings_not_the_newest(tmp_path, monkeypatch):
    """journald's SystemKeepFree=: room is made before writing, from the daemon's oldest recordings
    (issue 32, item 6); a write that cannot fit even so is refused, naming the shortfall."""
    old = [tmp_path / f"2020010{k}-000000-idle.npz" for k in range(1, 4)]
    for k, f in enumerate(old):
        f.write_bytes(b"x" * 300_000)
        os.utime(f, (k, k))
    (tmp_path / "my-data.npz").write_bytes(b"y" * 300_000)
    disk = Disk(tmp_path, capacity=10_000_000, other=8_400_000)       # 0.4 MB free of 10 MB
    monkeypatch.setattr(R.os, "statvfs", disk.statvfs)
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1, keep_free_mb=0.5)
    rec, events = run_recorder(params, episode(100.0, 1))
    written = [e for e in events if e["kind"] == "recording_written"]
    assert len(written) == 1 and os.path.exists(written[0]["path"]), events
    left = sorted(os.listdir(tmp_path))
    assert "my-data.npz" in left and old[-1].name in left and old[0].name not in left     # the oldest went
    # a disk that cannot take it even with every older recording gone: refused, and nothing deleted
    disk.other = 9_600_000
    before = sorted(os.listdir(tmp_path))
    rec, events = run_recorder(params, episode(200.0, 3))
    failed = [e for e in events if e["kind"] == "recording_failed"]
    assert len(failed) == 1 and "record.keep_free_mb" in failed[0]["message"], events
    assert sorted(os.listdir(tmp_path)) == before


def test_the_default_free_space_kept_is_journalds():
    import types
    big = types.SimpleNamespace(f_blocks=1 << 40, f_frsize=1)            # 1 TiB: capped at 4 GiB
    small = types.SimpleNamespace(f_blocks=10 << 30, f_frsize=1)         # 10 GiB: 15 %
    assert R.keep_free_bytes(None, big) == 4096 * 1024 * 1024
    assert R.keep_free_bytes(None, small) == pytest.approx(0.15 * (10 << 30))
    assert R.keep_free_bytes(100.0, big) == 100e6


def test_an_open_capture_is_written_every_checkpoint_and_closed_on_request(tmp_path):
    """What SIGKILL can cost is bounded: an open capture is on disk at its last checkpoint, a valid
    recording that says it is one (issue 32, item 5)."""
    params = R.RecordParams(dir=str(tmp_path), pre_onset_s=0.1, checkpoint_s=1.0)
    rec = R.Recorder(params, lambda *a, **k: None, {"robot": "sim", "imu_in_tcp_quat": [0, 0, 0, 1],
                                                    "plane_normal": None})
    stop = threading.Event()
    th = threading.Thread(target=rec.run, args=(stop,))
    th.start()
    try:
        rec.request("start", "long")
        for k in range(150):                     # 1.5 s of passes, fed in real time
            rec.feed(a_pass(100.0 + 0.01 * k))
            time.sleep(0.01)
        deadline = time.monotonic() + 5.0
        while not os.listdir(tmp_path) and time.monotonic() < deadline:
            time.sleep(0.05)
        (name,) = os.listdir(tmp_path)
        part = load_recording(tmp_path / name)
        assert part.meta["ended"].startswith("still open: a checkpoint")
        rec.close_capture("daemon stopping")
        deadline = time.monotonic() + 5.0
        while not rec.idle and time.monotonic() < deadline:
            time.sleep(0.05)
        whole = load_recording(tmp_path / name)
        assert whole.meta["ended"] == "daemon stopping" and len(whole.imu_t) > len(part.imu_t)
        assert os.listdir(tmp_path) == [name]
    finally:
        stop.set()
        th.join(5.0)


def test_captures_on_demand_are_limited_in_number_and_rate(tmp_path):
    rec = R.Recorder(R.RecordParams(dir=str(tmp_path), max_on_demand_burst=3, max_on_demand_per_min=1.0),
                     lambda *a, **k: None, {})
    for _ in range(3):
        assert rec.request("start", "x")["ok"] is True
        rec.request("stop", "")
    from tecdard.api import commands as C
    with pytest.raises(C.CommandError) as refused:
        rec.request("start", "x")
    assert refused.value.code == C.RATE_LIMITED and "record.max_on_demand_per_min" in refused.value.message


def test_a_recorder_that_falls_behind_drops_and_counts_never_blocks(tmp_path):
    rec = R.Recorder(R.RecordParams(dir=str(tmp_path)), lambda *a, **k: None, {})
    t0 = time.monotonic()
    for k in range(R.QUEUE_STEPS + 100):                  # its thread is not running: nothing is taken
        rec.feed(a_pass(100.0 + 0.01 * k))
    assert rec.dropped_passes == 100 and time.monotonic() - t0 < 5.0


def test_hostile_live_keys_are_one_line_errors(tmp_path):
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1)
    _, events = run_recorder(params, episode(100.0, 1))
    path = [e for e in events if e["kind"] == "recording_written"][0]["path"]
    with np.load(path) as z:
        good = dict(z)
    for key, value, message in (("live_pass_end", good["live_pass_end"][::-1].copy(), "live_pass_end"),
                                ("live_changes", np.array("{not json"), "live_changes: not JSON"),
                                ("live_bias0", np.zeros(3), "live_bias0: expected shape (4,)"),
                                ("live_tcp_pass", good["live_tcp_pass"] + 10 ** 6, "live_tcp_pass")):
        bad = tmp_path / f"bad-{key}.npz"
        np.savez(bad, **{**good, key: value})
        res = tecdard("localize", bad)
        assert res.returncode == 2 and message in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


# -- tecdard plot ---------------------------------------------------------------------------------

def test_plot_draws_a_simulated_recording_with_its_truth(tmp_path):
    pytest.importorskip("matplotlib", reason="the `viz` extra, which `make test` installs")
    rec = tmp_path / "hinge.npz"
    assert tecdard("sim-record", str(rec), "--kind", "hinge").returncode == 0
    out = tmp_path / "hinge.png"
    res = tecdard("plot", str(rec), "-o", str(out))
    assert res.returncode == 0, res.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
    assert "estimates" in res.stdout


def test_plot_refuses_what_localize_refuses_with_the_same_line(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("tecdar-recording/1"), imu_t=np.zeros(3))
    plot, localize = tecdard("plot", str(bad), "-o", str(tmp_path / "x.png")), tecdard("localize", str(bad))
    assert plot.returncode == localize.returncode == 2
    assert plot.stderr.replace("tecdard plot:", "") == localize.stderr.replace("tecdard localize:", "")
    assert len(plot.stderr.strip().splitlines()) == 1


def test_plot_without_matplotlib_says_what_to_install_in_one_line(tmp_path):
    rec = tmp_path / "arc.npz"
    assert tecdard("sim-record", str(rec), "--kind", "edge-arc").returncode == 0
    code = ("import sys; sys.modules['matplotlib'] = None; from tecdard.cli.main import main; "
            f"sys.exit(main(['plot', {str(rec)!r}, '-o', {str(tmp_path / 'x.png')!r}]))")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip() == "tecdard plot: needs matplotlib: pip install 'tecdar[viz]'"


# -- tecdard export --mcap ----------------------------------------------------------------------------

def read_mcap(path) -> dict:
    """topic -> [(schema name, log_time, data bytes)], read back with the mcap package's reader."""
    from mcap.reader import make_reader
    out: dict = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            out.setdefault(channel.topic, []).append((schema.name, message.log_time, message.data))
    return out


def check_export(rec_path, mcap_path, *extra) -> dict:
    res = tecdard("export", str(rec_path), "--mcap", str(mcap_path), *extra)
    assert res.returncode == 0, res.stderr
    topics = read_mcap(mcap_path)
    rec = load_recording(rec_path)
    assert {name for name, _, _ in topics["/tf"]} == {"foxglove.FrameTransforms"}
    # one per proprioception sample, and the arm's root link placed once with its description
    assert len(topics["/tf"]) == len(rec.tcp_t) + ("/robot_description" in topics)
    means = [json.loads(d) for _, _, d in topics["/imu/mean"]]     # what a Plot panel draws: scalars
    assert len(means) == len(topics["/imu"]) and set(means[0]["gyro"]) == {"x", "y", "z"}
    assert {name for name, _, _ in topics["/contact"]} == {"foxglove.SceneUpdate"}
    assert {name for name, _, _ in topics["/events"]} == {"foxglove.Log"}
    imu = [json.loads(d) for _, _, d in topics["/imu"]]
    assert sum(len(m["t"]) for m in imu) == len(rec.imu_t)        # every sample, batched
    assert len(imu) >= (rec.imu_t[-1] - rec.imu_t[0]) / 0.011
    np.testing.assert_array_equal(np.concatenate([m["gyro"] for m in imu]), rec.gyro)
    times = [t for msgs in topics.values() for _, t, _ in msgs]
    assert min(times) >= 0
    return topics


def test_export_writes_the_imu_the_tcp_the_estimate_and_the_events_as_mcap(tmp_path):
    pytest.importorskip("foxglove", reason="the `viz` extra, which `make test` installs")
    rec = tmp_path / "hinge.npz"
    assert tecdard("sim-record", str(rec), "--kind", "hinge").returncode == 0
    topics = check_export(rec, tmp_path / "hinge.mcap")
    n_est = len(L.replay(load_recording(rec), ContactPipeline.from_config(
        Config({}).section("estimator"), np.eye(3), 6667.0))[0])
    assert len(topics["/contact"]) == n_est + 1                    # each estimate, and the truth
    assert any(b"contact_onset" in d for _, _, d in topics["/events"])


def test_export_refuses_what_localize_refuses_and_an_unwritable_path(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("tecdar-recording/1"), imu_t=np.zeros(3))
    res, localize = tecdard("export", str(bad), "--mcap", str(tmp_path / "x.mcap")), tecdard("localize", str(bad))
    assert res.returncode == 2 and res.stderr.replace("export", "localize") == localize.stderr
    rec = tmp_path / "arc.npz"
    assert tecdard("sim-record", str(rec), "--kind", "edge-arc").returncode == 0
    res = tecdard("export", str(rec), "--mcap", str(tmp_path / "no" / "such" / "dir" / "x.mcap"))
    assert res.returncode == 2 and res.stderr.startswith("tecdard export: --mcap: cannot write")
    assert len(res.stderr.strip().splitlines()) == 1


def test_sigterm_during_a_capture_writes_it_and_sigkill_costs_at_most_a_checkpoint(tmp_path):
    """6 of 7 captures of 20-45 s were lost to SIGTERM: the shutdown waited 0.5 s for the recorder
    (issue 32, item 5). Now the capture is closed at once and written while the arm stops; and
    SIGKILL leaves the last checkpoint."""
    import signal
    (tmp_path / "term").mkdir()
    d = DaemonProcess(tmp_path / "term", daemon_config())
    try:
        assert d.client.command("record", {"action": "start", "label": "long"})["ok"] is True
        time.sleep(20.0)
        t0 = time.monotonic()
        assert d.terminate(signal.SIGTERM, timeout=10.0) == 0
        stop_s = time.monotonic() - t0
    finally:
        d.close()
    (name,) = os.listdir(tmp_path / "term" / "recordings")
    rec = load_recording(tmp_path / "term" / "recordings" / name)
    assert rec.meta["ended"] == "daemon stopping" and rec.imu_t[-1] - rec.imu_t[0] > 19.0
    assert stop_s < 5.0, f"stopped in {stop_s:.1f} s: over the unit's TimeoutStopSec"
    (tmp_path / "kill").mkdir()
    d = DaemonProcess(tmp_path / "kill", daemon_config(**{"record.checkpoint_s": 2.0}))
    try:
        assert d.client.command("record", {"action": "start"})["ok"] is True
        time.sleep(5.0)
        d.terminate(signal.SIGKILL)
    finally:
        d.close()
    files = [f for f in os.listdir(tmp_path / "kill" / "recordings") if not f.startswith(".")]
    (name,) = files
    rec = load_recording(tmp_path / "kill" / "recordings" / name)
    assert rec.meta["ended"].startswith("still open: a checkpoint") and rec.imu_t[-1] - rec.imu_t[0] > 2.5


def test_a_task_is_never_filed_inside_an_idle_capture(tmp_path):
    """Issue 33: a spurious onset after a task's end opened an idle capture, and the next task was
    filed inside it. Whatever the trigger does, an idle capture closes before the task's first pass."""
    from tecdard.recording.format import load_recording
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1)
    items = [("feed", a_pass(0.01 * k, episode=1)) for k in range(10)]
    items.append(("feed", a_pass(0.1, episode=1, onset=True, est=True)))          # an onset at rest, no task
    items += [("feed", a_pass(0.11 + 0.01 * k, episode=1, est=True)) for k in range(10)]
    items.append(("note_event", {"kind": "task_started", "task": "rotate-1", "verb": "rotate", "t": 0.21}))
    items += [("feed", a_pass(0.21 + 0.01 * k, episode=2)) for k in range(10)]     # the task's own episode
    items.append(("feed", a_pass(0.31, episode=2, onset=True, est=True)))
    items += [("feed", a_pass(0.32 + 0.01 * k, episode=2, est=True)) for k in range(10)]
    items.append(("note_event", {"kind": "task_done", "task": "rotate-1", "verb": "rotate", "t": 0.42}))
    rec, events = run_recorder(params, items)
    written = sorted(tmp_path.glob("*.npz"))
    assert [p.name.split("-", 2)[2] for p in written] == ["idle.npz", "rotate-1.npz"], written
    idle = load_recording(written[0])
    assert idle.meta["task"] is None and float(idle.imu_t[-1]) < 0.21      # nothing of the task's passes
    task = load_recording(written[1])
    assert task.meta["task"] == "rotate-1" and float(task.imu_t[0]) >= 0.21 - params.pre_onset_s


def test_a_tasks_onset_that_reaches_the_recorder_before_its_start_event_is_filed_with_the_task(tmp_path):
    """A fresh clone's run: a commanded onset is dated at the task's first tick, and its pass reached the recorder
    before the task's start event did. That opened an idle capture, and the start event closed it as
    `...-idle.npz`. Now the task adopts it: one file, the task's, and no idle one."""
    from tecdard.recording.format import load_recording
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1)
    items = [("feed", a_pass(0.01 * k, episode=1)) for k in range(10)]
    items.append(("feed", a_pass(0.1, episode=2, onset=True, est=True)))           # the task's first tick, 0.1
    items.append(("note_event", {"kind": "task_started", "task": "probe-1", "verb": "probe", "t": 0.102}))
    items += [("feed", a_pass(0.11 + 0.01 * k, episode=2, est=True)) for k in range(10)]
    items.append(("note_event", {"kind": "task_done", "task": "probe-1", "verb": "probe", "t": 0.22}))
    # and an idle onset well before a task's start is still an idle capture of its own
    items += [("feed", a_pass(0.3 + 0.01 * k, episode=3)) for k in range(5)]
    items.append(("feed", a_pass(0.35, episode=3, onset=True, est=True)))
    items += [("feed", a_pass(0.36 + 0.01 * k, episode=3, est=True)) for k in range(10)]
    items.append(("note_event", {"kind": "task_started", "task": "probe-2", "verb": "probe", "t": 0.6}))
    run_recorder(params, items)
    written = sorted(tmp_path.glob("*.npz"))
    assert [p.name.split("-", 2)[2] for p in written] == ["idle.npz", "probe-1.npz"], written
    task = load_recording(written[1])
    assert task.meta["task"] == "probe-1" and float(task.imu_t[0]) <= 0.1


def test_an_idle_capture_is_closed_after_max_idle_capture_s(tmp_path):
    """One idle capture ran 113 s on an arm at rest: it is closed after record.max_idle_capture_s."""
    params = R.RecordParams(enabled=True, dir=str(tmp_path), pre_onset_s=0.1, max_idle_capture_s=0.5)
    rec = R.Recorder(params, lambda kind, **f: None, {"robot": "sim", "imu_in_tcp_quat": [0, 0, 0, 1],
                                                      "plane_normal": None})
    stop = threading.Event()
    th = threading.Thread(target=rec.run, args=(stop,))
    th.start()
    try:
        rec.feed(a_pass(0.0, episode=1))
        rec.feed(a_pass(0.01, episode=1, onset=True, est=True))
        t_open = time.monotonic()
        k = 0
        while rec._capture is None or time.monotonic() - t_open < 2.0:
            k += 1
            rec.feed(a_pass(0.02 + 0.01 * k, episode=1, est=True))
            time.sleep(0.01)
            if rec._capture is None and time.monotonic() - t_open > 0.3:
                break
        closed_after = time.monotonic() - t_open
    finally:
        stop.set()
        th.join(10.0)
    assert closed_after < 1.5 and list(tmp_path.glob("*-idle.npz")), closed_after


def test_plot_reads_as_a_person_reads_it(tmp_path):
    """Issue 33: the plot in mm, the unobservable axis said instead of banded, the TCP, the angle, the
    task's marks, and the error panel with a truth (the figure's text, drawn as SVG text)."""
    pytest.importorskip("matplotlib", reason="the `viz` extra, which `make test` installs")
    import matplotlib
    from tecdard.recording.format import load_recording, load_truth
    from tecdard.tools.plot import draw
    rec_path = tmp_path / "arc.npz"
    assert tecdard("sim-record", str(rec_path), "--kind", "edge-arc", "--radius", "0.12").returncode == 0
    rec = load_recording(rec_path)
    truth = load_truth(rec_path)
    t = rec.imu_t
    onset = float(t[len(t) // 3])
    k = np.arange(50)
    rows = np.column_stack([onset + 0.01 * k, np.tile(truth["p_c"], (50, 1)) + 1e-3,
                            np.tile([0.004, 0.5, 0.003], (50, 1))])
    events = [{"kind": "task_started", "t": float(t[0]) + 0.1}, {"kind": "task_done", "t": float(t[-1]) - 0.1}]
    out = tmp_path / "arc.svg"
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        draw(rec, rows, onset, truth, str(out), "arc", fmt="svg", events=events)
    text = out.read_text()
    for label in ("contact x, mm", "unobservable", "(one-sigma 500 mm)", "TCP from its start", "fingertip turned",
                  "since the onset, deg", "error, mm", "onset", "start", "done", "time since the recording"):
        assert label in text, label
    assert text.count("±3σ") == 2                  # x and z banded; y, along the hinge, not


def test_a_capture_on_demand_that_closed_itself_at_its_limit_does_not_leave_start_busy(tmp_path):
    """Issue 50 item 7: a capture on demand closes itself after MAX_CAPTURE_S (120 s); `record start` then
    answered `busy` until someone sent `record stop`."""
    from tecdard.api import commands as C
    rec = R.Recorder(R.RecordParams(dir=str(tmp_path)), lambda *a, **k: None, {})
    assert rec.request("start", "long")["ok"] is True
    rec._on_command("start", "long")                     # the recorder thread opens it
    with pytest.raises(C.CommandError) as busy:
        rec.request("start", "again")                     # still running: busy, as before
    assert busy.value.code == C.BUSY
    rec._capture.t_open -= R.MAX_CAPTURE_S + 1.0
    rec._check_age()                                      # the recorder thread closes it at its limit
    assert rec._capture is None
    reply = rec.request("start", "next")
    assert reply["ok"] is True and reply["label"] == "next"
