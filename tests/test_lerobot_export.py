"""Issue 52, item 3: daemon recordings as a LeRobot v3 dataset (`tecdard export --lerobot`).

The recordings here are built by hand, so that every frame's expected content is known: a board at 6667 Hz, an
arm at 500 Hz, control ticks at 50 Hz that run up to 3 ms late and once not at all (an overrun). The oracle for
the layout is Hugging Face's `datasets`, which lerobot loads a dataset's Parquet files with: the same
Dataset.from_parquet call with the features lerobot 0.4.4 derives from info.json (its
get_hf_features_from_features, re-stated here: importing lerobot pulls in torch). A daemon's own recording is
exported in tests/test_recorder.py."""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import tecdard
from tests.test_offline_outputs import live_keys

pa = pytest.importorskip("pyarrow", reason="the lerobot extra (pyarrow) is installed by `make test`")
import pyarrow.parquet as pq  # noqa: E402

ODR, ARM_HZ, FPS, JOINTS = 6667.0, 500.0, 50, 7
T0 = 1000.0
SKIPPED_TICK = 40                # an overrun: the tick that never ran (the one before held)


def daemon_recording(path, seconds: float = 3.0, seed: int = 0, verb: str = "rotate") -> dict:
    """A daemon recording's members with known content; written to `path`, and returned."""
    rng = np.random.default_rng(seed)
    n_imu, n_arm = int(seconds * ODR), int(seconds * ARM_HZ)
    imu_t = T0 + np.arange(n_imu) / ODR
    tcp_t = T0 + 0.0004 + np.arange(n_arm) / ARM_HZ
    ticks = [k for k in range(int(seconds * FPS)) if k != SKIPPED_TICK]
    cmd_t = T0 + 0.01 + np.array(ticks) / FPS + rng.uniform(0.0, 0.003, len(ticks))    # late by up to 3 ms
    cmd = np.column_stack([cmd_t, np.outer(ticks, np.ones(JOINTS)) * 1e-3])               # joint rate = tick / 1000
    arrays = {"format": np.array("tecdar-recording/1"), "imu_t": imu_t,
              "gyro": rng.normal(0.0, 0.1, (n_imu, 3)), "accel": rng.normal(0.0, 1.0, (n_imu, 3)) + [0, 0, 9.81],
              "tcp_t": tcp_t, "tcp_pos": np.column_stack([0.4 + 1e-3 * np.arange(n_arm) / ARM_HZ,
                                                          np.zeros(n_arm), np.full(n_arm, 0.5)]),
              "tcp_quat": np.tile([0.0, 0.0, 0.0, 1.0], (n_arm, 1)), "imu_in_tcp_quat": np.array([0.0, 0, 0, 1]),
              "meta": np.array(json.dumps({"robot": "sim", "task": f"{verb}-1", "verb": verb}))}
    est_t = T0 + 1.5 + np.arange(20) * 0.05
    events = [{"t": T0 + 0.2, "kind": "task_started", "task": f"{verb}-1", "verb": verb,
               "params": {"angle_deg": 30.0, "speed": 0.02}},
              {"t": T0 + 1.4, "kind": "contact_onset"},
              {"t": T0 + 2.9, "kind": "task_done", "task": f"{verb}-1", "result": {"angle_deg": 30.1}}]
    arrays |= live_keys(arrays, events) | {
        "live_est": np.column_stack([est_t, np.tile([0.15, 0.0, 0.49], (20, 1)), np.full((20, 3), 0.004)]),
        "live_axis": np.tile([0.0, 1.0, 0.0], (20, 1)),
        "live_q": np.outer(np.arange(n_arm), np.ones(JOINTS)) * 1e-4,
        "live_qd": np.full((n_arm, JOINTS), 0.05),
        "tcp_wrench": np.column_stack([np.full((n_arm, 3), 2.0), np.full((n_arm, 3), np.nan)]),
        "live_cmd": cmd}
    np.savez(path, **arrays)
    return arrays


def hf_features(features: dict):
    """lerobot 0.4.4's datasets/utils.py get_hf_features_from_features, for the shapes we write."""
    import datasets
    out = {}
    for key, ft in features.items():
        shape = tuple(ft["shape"])
        if shape == (1,):
            out[key] = datasets.Value(dtype=ft["dtype"])
        elif len(shape) == 1:
            out[key] = datasets.Sequence(length=shape[0], feature=datasets.Value(dtype=ft["dtype"]))
        else:
            out[key] = datasets.Array2D(shape=shape, dtype=ft["dtype"])
    return datasets.Features(out)


@pytest.mark.slow
def test_each_frame_holds_the_ticks_action_the_newest_state_and_the_imu_window_ending_at_it(tmp_path):
    arrays = [daemon_recording(tmp_path / f"ep{k}.npz", seed=k, verb=verb) for k, verb in enumerate(("rotate", "probe"))]
    out = tmp_path / "ds"
    res = tecdard("export", "--lerobot", str(out), str(tmp_path / "ep0.npz"), str(tmp_path / "ep1.npz"))
    assert res.returncode == 0, res.stderr
    info = json.loads((out / "meta" / "info.json").read_text())
    assert (info["codebase_version"], info["fps"], info["total_episodes"], info["total_tasks"]) == ("v3.0", 50, 2, 2)
    n = round(ODR / FPS)
    assert info["features"]["observation.imu"]["shape"] == [n, 6] and n == 133
    table = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet").to_pydict()
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert info["total_frames"] == len(table["index"]) == sum(e["length"] for e in episodes)
    for e, (ep, a) in enumerate(zip(episodes, arrays)):
        rows = range(ep["dataset_from_index"], ep["dataset_to_index"])
        assert [table["episode_index"][i] for i in rows] == [e] * len(rows)
        assert [table["frame_index"][i] for i in rows] == list(range(len(rows)))
        cmd_t, imu_t, tcp_t = a["live_cmd"][:, 0], a["imu_t"], a["tcp_t"]
        t_first = max(cmd_t[0], tcp_t[0], imu_t[n - 1])
        assert len(rows) == int((min(cmd_t[-1], tcp_t[-1], imu_t[-1]) - t_first) * FPS) + 1
        for f in (0, 1, SKIPPED_TICK - 1, len(rows) - 1):
            i, t = rows[f], t_first + f / FPS
            assert table["timestamp"][i] == pytest.approx(f / FPS, abs=1e-6)
            # the tick scheduled at t (run up to 3 ms late), or where it never ran the one before
            tick = max(k for k in range(len(cmd_t)) if cmd_t[k] <= t + 0.5 / FPS)
            np.testing.assert_allclose(table["action"][i], a["live_cmd"][tick, 1:], rtol=1e-6)
            j = max(k for k in range(len(tcp_t)) if tcp_t[k] <= t)
            state = np.concatenate([a["live_q"][j], a["live_qd"][j], a["tcp_pos"][j], a["tcp_quat"][j]])
            np.testing.assert_allclose(table["observation.state"][i], state, rtol=1e-6, atol=1e-7)
            last = max(k for k in range(len(imu_t)) if imu_t[k] <= t)
            window = np.column_stack([a["gyro"], a["accel"]])[last - n + 1:last + 1]
            np.testing.assert_allclose(table["observation.imu"][i], window, rtol=1e-6, atol=1e-6)
            wrench = np.array(table["observation.wrench"][i], float)
            assert np.allclose(wrench[:3], 2.0) and np.all(np.isnan(wrench[3:]))      # the arm gave no torque
        # the skipped tick's frame holds the tick before it
        f = next(f for f in range(len(rows)) if t_first + f / FPS >= cmd_t[SKIPPED_TICK - 1] + 0.5 / FPS)
        assert table["action"][rows[f]][0] == pytest.approx((SKIPPED_TICK - 1) * 1e-3, rel=1e-6)
        contact = np.array([table["observation.contact"][i] for i in rows], float)
        before = np.array([t_first + f / FPS < a["live_est"][0, 0] for f in range(len(rows))])
        assert np.all(contact[before, 9] == 0.0) and np.all(np.isnan(contact[before, :9]))
        np.testing.assert_allclose(contact[~before][-1], [0.15, 0.0, 0.49, 0, 1, 0, 0.004, 0.004, 0.004, 1.0],
                                   rtol=1e-6)
        meta = json.loads(ep["tecdar"])
        assert meta["verb"] == ("rotate", "probe")[e] and meta["outcome"] == "task_done"
        assert meta["onsets_s"] == [pytest.approx(T0 + 1.4 - t_first, abs=1e-9)]
    tasks = pq.read_table(out / "meta" / "tasks.parquet").to_pylist()
    assert {t["task"] for t in tasks} == {"rotate angle_deg=30.0 speed=0.02", "probe angle_deg=30.0 speed=0.02"}
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert set(stats) == set(info["features"])
    assert np.array(stats["observation.imu"]["mean"]).shape == (n, 6) and stats["action"]["count"] == [len(table["index"])]
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}
    assert "LeRobot" in (out / "README.md").read_text()


@pytest.mark.slow
def test_the_dataset_loads_as_lerobot_loads_it(tmp_path):
    datasets = pytest.importorskip("datasets", reason="the lerobot-test extra is installed by `make test`")
    daemon_recording(tmp_path / "ep.npz")
    out = tmp_path / "ds"
    assert tecdard("export", "--lerobot", str(out), str(tmp_path / "ep.npz")).returncode == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    ds = datasets.Dataset.from_parquet([str(p) for p in sorted((out / "data").glob("*/*.parquet"))],
                                       features=hf_features(info["features"])).with_format("numpy")
    assert len(ds) == info["total_frames"]
    row = ds[10]
    for key, ft in info["features"].items():
        assert np.asarray(row[key]).shape == (tuple(ft["shape"]) if ft["shape"] != [1] else ()), key
    assert row["observation.imu"].dtype == np.float32 and row["timestamp"] == pytest.approx(10 / FPS)


@pytest.mark.parametrize("why, argv, said", [
    ("no action in a recording", ["--lerobot", "{out}", "{plain}"], "no live_cmd"),
    ("a dataset already there", ["--lerobot", "{full}", "{rec}"], "is there and not an empty directory"),
    ("--mcap with two recordings", ["--mcap", "{out}.mcap", "{rec}", "{rec}"], "--mcap: one recording, got 2"),
    ("--store without --query", ["--lerobot", "{out}", "--store", "file:///nowhere"], "--store and --query go together"),
    ("--method with --lerobot", ["--lerobot", "{out}", "--method", "ekf", "{rec}"], "go with --mcap"),
    ("nothing named", ["--lerobot", "{out}"], "no recordings"),
])
def test_bad_exports_are_one_line_refusals_that_write_nothing(tmp_path, why, argv, said):
    arrays = daemon_recording(tmp_path / "rec.npz")
    np.savez(tmp_path / "plain.npz", **{k: v for k, v in arrays.items() if k != "live_cmd"})
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("a lab's file")
    names = {"out": tmp_path / "ds", "rec": tmp_path / "rec.npz", "plain": tmp_path / "plain.npz",
             "full": tmp_path / "full"}
    res = tecdard("export", *[a.format(**names) for a in argv])
    err = res.stderr.strip()
    assert res.returncode == 2 and len(err.splitlines()) == 1 and said in err, (why, err)
    assert not (tmp_path / "ds").exists() and (tmp_path / "full" / "x").read_text() == "a lab's file", why


@pytest.mark.slow
def test_a_query_over_the_episode_index_picks_the_episodes(tmp_path):
    """`--store URL --query SQL`: the recordings a lab uploaded (`tecdard episodes sync`), picked by the index."""
    pytest.importorskip("duckdb", reason="the fleet extra is installed by `make test`")
    rec = tmp_path / "rec"
    rec.mkdir()
    for k, verb in enumerate(("rotate", "probe", "rotate")):
        daemon_recording(rec / f"20261207-12000{k}-{verb}.npz", seconds=2.0, seed=k, verb=verb)
    url = f"file://{tmp_path}/store"
    res = tecdard("episodes", "sync", "--dir", str(rec), "--store", url, "--robot", "arm1")
    assert res.returncode == 0, res.stderr
    out = tmp_path / "ds"
    res = tecdard("export", "--lerobot", str(out), "--store", url, "--query",
                  "SELECT npz_key FROM episodes WHERE verb = 'rotate' ORDER BY npz_key")
    assert res.returncode == 0, res.stderr
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [json.loads(e["tecdar"])["verb"] for e in episodes] == ["rotate", "rotate"]
    res = tecdard("export", "--lerobot", str(tmp_path / "ds2"), "--store", url, "--query", "SELECT verb FROM episodes")
    assert res.returncode == 2 and "have no npz_key" in res.stderr and not (tmp_path / "ds2").exists()
