"""Every contact episode in one store: uploads to a local-file store and to S3 (moto's server on loopback, standing
in for MinIO or AWS), at most one copy whatever is retried, the store going away and coming back, two writers at
once, the Parquet index under DuckDB, a corrupt or hostile index file, and the recorder deleting only what the
store has."""
import concurrent.futures
import json
import pathlib
import shutil
import threading
import time
import uuid

import numpy as np
import pytest

from tecdard.fleet.episodes import (EpisodeStore, StoreError, StoreParams, index_key, is_uploaded, read_episode,
                                    upload)
from tecdard.fleet.index import Index, compact, query
from tecdard.runtime.uploader import Uploader
from tecdard.tools.demo import free_port
from tests.conftest import tecdard
from tests.test_localize import scenario_file

ROBOT = "arm-a"
EPISODES = 3
ERROR_M = 0.003                # a simulated edge's contact found within 3 mm of its truth
UPLOAD_WAIT_S = 60.0
S3_KEYS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_REGION": "us-east-1"}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """EPISODES short simulated edge contacts, named as the daemon names its recordings."""
    folder = tmp_path_factory.mktemp("recordings")
    for k in range(EPISODES):
        scenario_file(folder / f"20261204-12000{k}-task{k}.npz", kind="edge-arc", seed=10 + k, duration_s=0.6)
    return folder


def fresh_copy(src: pathlib.Path, dst: pathlib.Path) -> pathlib.Path:
    dst.mkdir(parents=True, exist_ok=True)
    for f in src.glob("*.npz"):
        shutil.copy(f, dst / f.name)
    return dst


def objects(store: EpisodeStore, prefix: str = "") -> list[str]:
    return sorted(str(m["path"]) for m in store.list(prefix))


@pytest.fixture
def s3(monkeypatch):
    """moto's S3 server on a free loopback port with a bucket of its own (moto keeps every server's
    buckets in one process-wide backend); (StoreParams, S3Server)."""
    import boto3
    for key, value in S3_KEYS.items():
        monkeypatch.setenv(key, value)
    server = S3Server(free_port())
    bucket = f"tecdar-{uuid.uuid4().hex[:12]}"
    boto3.client("s3", endpoint_url=server.endpoint, region_name="us-east-1").create_bucket(Bucket=bucket)
    yield StoreParams(url=f"s3://{bucket}/lab", endpoint=server.endpoint, region="us-east-1", allow_http=True), server
    server.stop()


class S3Server:
    """moto's server mode on 127.0.0.1:port, stopped and started again on the same port as a store's outage."""

    def __init__(self, port: int):
        self.port, self.endpoint = port, f"http://127.0.0.1:{port}"
        self.server = None
        self.start()

    def start(self) -> None:
        from moto.server import ThreadedMotoServer
        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self.server.start()

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None


@pytest.mark.slow
def test_an_episode_goes_up_once_and_its_rows_answer_sql(tmp_path, recordings):
    rec = fresh_copy(recordings, tmp_path / "rec")
    store = EpisodeStore(StoreParams(url=f"file://{tmp_path}/store"))
    first = sorted(rec.glob("*.npz"))[0]
    ep = upload(store, first, robot=ROBOT, mcap=True)
    assert is_uploaded(first, store.url)
    assert ep.key(".npz") == f"{ROBOT}/{ep.day}/{first.stem}.npz"
    assert objects(store, ROBOT) == sorted([ep.key(".npz"), ep.key(".mcap")])
    assert (tmp_path / "store" / ep.key(".npz")).read_bytes() == first.read_bytes()
    # again, as after a crash before the local mark: nothing new, nothing doubled
    before = objects(store)
    upload(store, first, robot=ROBOT)
    assert objects(store) == before
    cols, rows = query(Index(store), "SELECT id, robot, contacts, duration_s FROM episodes")
    assert rows == [(ep.id, ROBOT, 1, pytest.approx(1.1, abs=0.01))]
    _, contacts = query(Index(store), "SELECT n, error_m, sigma_m, x_m FROM contacts")
    assert len(contacts) == 1 and contacts[0][1] < ERROR_M, contacts


def test_a_copy_in_another_store_never_counts_for_the_daemons_own(tmp_path, recordings):
    """Issue 50 item 2: after `episodes sync` to a try-out store (or a changed store.url) the `.uploaded` marker
    counted for every store: the uploader never uploaded those recordings to the daemon's own store, and the
    recorder's budget deleted them. A marker names each store that has the recording."""
    rec = fresh_copy(recordings, tmp_path / "rec")
    tryout = EpisodeStore(StoreParams(url=f"file://{tmp_path}/tryout"))
    own = StoreParams(url=f"file://{tmp_path}/own/")
    path = sorted(rec.glob("*.npz"))[0]
    upload(tryout, path, robot=ROBOT, mcap=False)
    uploader = Uploader(own, str(rec), ROBOT, lambda kind, **f: None)
    assert is_uploaded(path, tryout.url) and not is_uploaded(path, own.url)
    assert not uploader.may_delete(path)                            # the recorder's budget keeps it
    assert path in uploader._scan()                                 # and the uploader has it to do
    upload(EpisodeStore(own), path, robot=ROBOT, mcap=False)
    assert uploader.may_delete(path) and is_uploaded(path, tryout.url)       # both stores named now
    old = path.with_name(path.name + ".uploaded")                   # a marker of the older form: its one store
    old.write_text(json.dumps({"store": tryout.url, "key": "k", "at": "t"}))
    assert is_uploaded(path, tryout.url) and not uploader.may_delete(path)
    old.write_text("{not json")                                     # unreadable: kept, and uploaded again
    assert not uploader.may_delete(path)


@pytest.mark.slow
def test_sync_to_a_new_store_uploads_what_another_store_has(tmp_path, recordings):
    rec = fresh_copy(recordings, tmp_path / "rec")
    for name in ("one", "two"):
        res = tecdard("episodes", "sync", "--dir", str(rec), "--store", f"file://{tmp_path}/{name}", "--robot", ROBOT)
        assert res.returncode == 0, res.stderr
        n = len(list(rec.glob("*.npz")))
        assert f"{n} uploaded, 0 failed, 0 there already" in res.stderr, res.stderr


def test_a_store_that_has_another_file_of_that_name_is_never_overwritten(tmp_path, recordings):
    rec = fresh_copy(recordings, tmp_path / "rec")
    store = EpisodeStore(StoreParams(url=f"file://{tmp_path}/store"))
    path = sorted(rec.glob("*.npz"))[0]
    ep = read_episode(path, ROBOT)
    store.put_once(ep.key(".npz"), b"someone else's")
    with pytest.raises(StoreError, match="not these"):
        upload(store, path, robot=ROBOT, mcap=False)
    assert store.get(ep.key(".npz")) == b"someone else's" and not is_uploaded(path, store.url)


@pytest.mark.slow
def test_sync_query_fetch_through_the_command_line_on_s3(tmp_path, recordings, s3, monkeypatch):
    params, _server = s3
    rec = fresh_copy(recordings, tmp_path / "rec")
    opts = ["--store", params.url, "--endpoint", params.endpoint, "--region", "us-east-1", "--allow-http"]
    res = tecdard("episodes", "sync", "--dir", rec, "--robot", ROBOT, *opts)
    assert res.returncode == 0, res.stderr
    assert f"{EPISODES} uploaded, 0 failed" in res.stderr
    res = tecdard("episodes", "query", "SELECT count(*) AS n, sum(contacts) AS c FROM episodes", "--json", *opts)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == [{"n": EPISODES, "c": EPISODES}]
    # again: everything was there, nothing doubled
    res = tecdard("episodes", "sync", "--dir", rec, "--robot", ROBOT, "--again", *opts)
    assert res.returncode == 0 and f"{EPISODES} uploaded" in res.stderr, res.stderr
    store = EpisodeStore(params)
    assert len(objects(store, ROBOT)) == 2 * EPISODES                   # .npz and .mcap each
    assert len(objects(store, "index/episodes/")) == EPISODES
    res = tecdard("episodes", "query", "SELECT id FROM episodes ORDER BY id", "--csv", *opts)
    first_id = res.stdout.splitlines()[1]
    out = tmp_path / "back"
    res = tecdard("episodes", "fetch", first_id, "-o", out, "--mcap", *opts)
    assert res.returncode == 0, res.stderr
    name = first_id.split("/")[1]
    assert (out / f"{name}.npz").read_bytes() == (rec / f"{name}.npz").read_bytes()
    assert (out / f"{name}.mcap").stat().st_size > 0
    res = tecdard("localize", out / f"{name}.npz", "--json")
    assert res.returncode == 0, res.stderr
    # fetched twice: refused, nothing overwritten
    res = tecdard("episodes", "fetch", first_id, "-o", out, *opts)
    assert res.returncode == 2 and "not overwritten" in res.stderr


@pytest.mark.slow
def test_a_key_the_store_client_refuses_is_left_out_and_the_rest_answers(tmp_path, recordings, s3):
    """Issue 50 item 5: one key with a `..` segment in the bucket's index prefix made every query, fetch and
    compact fail (obstore refuses such a key, and the whole page of a listing with it). Now the prefix is listed
    again through botocore: each refused key is said once and left out, every other row answers (arm-0's,
    which shares a page with them), and compact and fetch work."""
    import boto3
    from tecdard.fleet.index import compact
    params, server = s3
    store = EpisodeStore(params)
    rec = sorted(fresh_copy(recordings, tmp_path / "rec").glob("*.npz"))
    for f in rec:
        upload(store, f, robot=ROBOT, mcap=False)
    upload(store, rec[0], robot="arm-0", mcap=False)          # a robot whose rows sort among the refused keys
    bucket = params.url.removeprefix("s3://").split("/")[0]
    s3c = boto3.client("s3", endpoint_url=params.endpoint, region_name="us-east-1")
    hostile = [f"lab/index/episodes/{ROBOT}/../x.parquet", "lab/index/episodes/../evil.parquet",
               "lab/index/episodes/./y.parquet", "lab/index/contacts/../z.parquet", f"lab/{ROBOT}//up.npz"]
    for key in hostile:
        s3c.put_object(Bucket=bucket, Key=key, Body=b"PAR1 not ours")
    opts = ["--store", params.url, "--endpoint", params.endpoint, "--region", "us-east-1", "--allow-http"]
    res = tecdard("episodes", "query", "SELECT count(*) AS n FROM episodes", "--json", *opts)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert json.loads(res.stdout) == [{"n": EPISODES + 1}], res.stderr
    said = res.stderr.strip().splitlines()
    assert len(said) == 4 and all("left out" in line and "refuses to name" in line for line in said), said
    index = Index(EpisodeStore(params))
    assert query(index, "SELECT count(*) FROM contacts")[1] == [(EPISODES + 1,)]
    assert sorted(k for k, _ in index.skipped) == sorted(k.removeprefix("lab/") for k in hostile[:4])
    merged = compact(EpisodeStore(params))
    assert merged["episodes"] == EPISODES + 1, merged
    assert query(Index(EpisodeStore(params)), "SELECT count(*) FROM episodes")[1] == [(EPISODES + 1,)]
    fetched = EpisodeStore(params)
    assert len(objects(fetched, ROBOT)) == EPISODES and fetched.bad_keys == [f"{ROBOT}//up.npz"]   # fetch's listing
    res = tecdard("episodes", "query", "SELECT id FROM episodes WHERE robot = 'arm-0'", "--csv", *opts)
    first_id = res.stdout.splitlines()[1]
    res = tecdard("episodes", "fetch", first_id, "-o", tmp_path / "back", *opts)
    assert res.returncode == 0, res.stderr


@pytest.mark.slow
def test_the_store_going_away_mid_upload_loses_nothing_and_doubles_nothing(tmp_path, recordings, s3):
    params, server = s3
    rec = fresh_copy(recordings, tmp_path / "rec")
    events: list[tuple[str, dict]] = []
    uploader = Uploader(StoreParams(**{**params.__dict__, "mcap": False, "retry_max_s": 2.0}), str(rec), ROBOT,
                        lambda kind, **f: events.append((kind, f)))
    # one episode half up before the outage: its recording there, its index rows not
    store = EpisodeStore(params)
    half = sorted(rec.glob("*.npz"))[0]
    ep = read_episode(half, ROBOT)
    store.put_once(ep.key(".npz"), half.read_bytes())
    server.stop()
    stop = threading.Event()
    th = threading.Thread(target=uploader.run, args=(stop,), daemon=True)
    th.start()
    try:
        _wait_for(lambda: any(k == "upload_failed" for k, _ in events), 30.0, lambda: events)
        assert not any(is_uploaded(f, store.url) for f in rec.glob("*.npz"))            # nothing marked while away
        server.start()
        _wait_for(lambda: all(is_uploaded(f, store.url) for f in rec.glob("*.npz")), UPLOAD_WAIT_S, lambda: events[-3:])
    finally:
        stop.set()
        th.join(5.0)
        if server.server is None:
            server.start()
    assert [f for k, f in events if k == "upload_failed" and f.get("retry")]     # it backed off and retried
    assert sum(k == "episode_uploaded" for k, _ in events) == EPISODES
    assert len(objects(store, ROBOT)) == EPISODES
    _, rows = query(Index(store), "SELECT count(*), count(DISTINCT id) FROM episodes")
    assert rows == [(EPISODES, EPISODES)]
    _, rows = query(Index(store), "SELECT count(*) FROM contacts")
    assert rows == [(EPISODES,)]


@pytest.mark.slow
def test_two_writers_and_a_compaction_at_once_lose_no_row(tmp_path, recordings):
    url = f"file://{tmp_path}/store"
    folders = []
    for writer in range(2):
        folder = tmp_path / f"w{writer}"
        for k in range(4):
            src = sorted(recordings.glob("*.npz"))[k % EPISODES]
            folder.mkdir(exist_ok=True)
            shutil.copy(src, folder / f"20261204-13{writer}0{k}0-task{k}.npz")
        folders.append(folder)

    def write(folder, robot):
        store = EpisodeStore(StoreParams(url=url))
        for f in sorted(folder.glob("*.npz")):
            upload(store, f, robot=robot, mcap=False)
            compact(store)

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        list(pool.map(write, folders, ["arm-a", "arm-b"]))
    store = EpisodeStore(StoreParams(url=url))
    _, rows = query(Index(store), "SELECT robot, count(*) FROM episodes GROUP BY robot ORDER BY robot")
    assert rows == [("arm-a", 4), ("arm-b", 4)]
    _, rows = query(Index(store), "SELECT count(*) FROM contacts")
    assert rows == [(8,)]
    compact(store)
    assert len(objects(store, "index/episodes/")) == 1
    _, rows = query(Index(store), "SELECT count(*), count(DISTINCT id) FROM episodes")
    assert rows == [(8, 8)]


@pytest.mark.slow
def test_a_corrupt_or_hostile_index_file_is_one_line_and_the_rest_answers(tmp_path, recordings):
    rec = fresh_copy(recordings, tmp_path / "rec")
    url = f"file://{tmp_path}/store"
    store = EpisodeStore(StoreParams(url=url))
    for f in rec.glob("*.npz"):
        upload(store, f, robot=ROBOT, mcap=False)
    good = tmp_path / "store" / "index" / "episodes" / ROBOT
    (good / "garbage.parquet").write_bytes(b"PAR1" + bytes(range(256)) * 40)
    import duckdb
    duckdb.sql(f"COPY (SELECT 'x' AS id, 42 AS robot) TO '{good / 'other-shape.parquet'}' (FORMAT parquet)")
    duckdb.sql(f"COPY (SELECT 1 AS surprise) TO '{good / 'foreign.parquet'}' (FORMAT parquet)")
    res = tecdard("episodes", "query", "SELECT count(*) AS n FROM episodes", "--json", "--store", url)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == [{"n": EPISODES}]
    said = res.stderr.strip().splitlines()
    assert len(said) == 3 and all("left out" in line for line in said), said
    assert "Traceback" not in res.stderr
    # SQL DuckDB refuses, and a store that is not there: one line each
    for args, fragment in ((["SELECT nope FROM episodes", "--store", url], "nope"),
                           (["SELECT 1", "--store", "ftp://x"], "expected file:///"),
                           (["SELECT 1"], "no store")):
        res = tecdard("episodes", "query", *args)
        assert res.returncode == 2 and fragment in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_the_recorder_deletes_only_what_the_store_has(tmp_path):
    from tecdard.runtime.recorder import Recorder, RecordParams
    folder = tmp_path / "rec"
    folder.mkdir()
    old = []
    for k in range(3):
        f = folder / f"20261204-10000{k}-t{k}.npz"
        f.write_bytes(b"x" * 400_000)
        old.append(f)
        time.sleep(0.01)
    own = StoreParams(url=f"file://{tmp_path}/store")
    (folder / (old[1].name + ".uploaded")).write_text(json.dumps({"stores": [{"store": own.url, "key": "k"}]}))
    (folder / (old[2].name + ".uploaded")).write_text(json.dumps({"stores": [{"store": "file:///elsewhere"}]}))
    recorder = Recorder(RecordParams(dir=str(folder), max_mb=1.0, keep_free_mb=0.0), lambda *a, **k: None, {})
    recorder.may_delete = Uploader(own, str(folder), ROBOT, lambda *a, **k: None).may_delete
    recorder._make_room(folder, 400_000, keep=folder / "20261204-110000-new.npz")
    assert old[0].exists() and old[2].exists()              # not in the daemon's store (old[2]: in another): kept
    assert not old[1].exists() and not (folder / (old[1].name + ".uploaded")).exists()


@pytest.mark.slow
def test_a_bad_store_config_is_one_line(tmp_path):
    from tests.conftest import daemon_config
    from tecdard.config import dump_yaml
    for store, fragment in (({"url": "http://x"}, "store.url"), ({"url": "file://relative"}, "absolute"),
                            ({"url": "s3://"}, "no bucket"), ({"urll": "x"}, "store.urll: unknown option")):
        cfg = tmp_path / "d.yaml"
        cfg.write_text(dump_yaml(daemon_config(store=store)))
        res = tecdard("run", "--config", cfg, timeout=60)
        assert res.returncode == 2 and fragment in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_daemons_recording_reaches_the_store_with_its_task_and_contact(make_daemon, tmp_path):
    from tests.conftest import rotate_on_the_cutter
    store_dir = tmp_path / "store"
    d = make_daemon(**{"store": {"url": f"file://{store_dir}"}, "record.enabled": True})
    rotate_on_the_cutter(d)
    # the arm's own wrench (issue 52): the simulator's contact force, its torque not modelled
    wrench = d.client.command("status")["state"]["wrench"]
    assert wrench["source"] == "sim_contact" and len(wrench["force_n"]) == 3 and wrench["torque_nm"] is None, wrench
    ev = d.client.wait_event(("episode_uploaded",), None, UPLOAD_WAIT_S)
    assert ev["store"] == f"file://{store_dir}"
    store = EpisodeStore(StoreParams(url=f"file://{store_dir}"))
    _, rows = query(Index(store), "SELECT robot, task, verb, result, backend, eta, contacts, peak_force_n FROM episodes")
    assert len(rows) >= 1
    robot, task, verb, result, backend, eta, contacts, peak = rows[0]
    assert (robot, verb, result, backend) == ("sim", "rotate", "done", "sim") and eta > 0 and contacts >= 1, rows
    # the handle pulls back on the grasp as it turns: a force, in newtons, no arm's ceiling
    assert peak is not None and 0.1 < peak < 1000.0, rows
    rec = next(store_dir.glob("sim/*/*.npz"))
    with np.load(rec) as z:
        w, meta, n_tcp = z["tcp_wrench"], json.loads(str(z["meta"])), len(z["tcp_t"])
    assert w.shape == (n_tcp, 6) and np.all(np.isfinite(w[:, :3]))
    assert np.all(np.isnan(w[:, 3:])) and meta["wrench_source"] == "sim_contact"
    assert abs(float(np.linalg.norm(w[:, :3], axis=1).max()) - peak) < 1e-2
    _, rows = query(Index(store), "SELECT error_m, sigma_m, converged_after_s FROM contacts ORDER BY n LIMIT 1")
    assert rows[0][0] is not None and rows[0][0] < ERROR_M, rows
    assert index_key("episodes", read_episode(next(store_dir.glob("sim/*/*.npz")), "sim")).startswith("index/")


def test_an_index_written_before_a_column_was_added_reads_it_as_null(tmp_path, recordings):
    """Index files written before `peak_force_n` existed (LATER_COLUMNS) are no foreign files: the view reads the
    column as NULL for them, beside a newer file that has it, and compaction keeps both rows."""
    from tecdard.fleet.episodes import EPISODE_COLUMNS, EPISODES_TABLE, INDEX, parquet_bytes
    store = EpisodeStore(StoreParams(url=f"file://{tmp_path / 'store'}"))
    old_columns = tuple(c for c in EPISODE_COLUMNS if c[0] != "peak_force_n")
    rows = [{"id": "old-1", "robot": "a", "episode": "e1", "contacts": 1},
            {"id": "new-1", "robot": "a", "episode": "e2", "contacts": 1, "peak_force_n": 12.5}]
    store.put_once(f"{INDEX}/{EPISODES_TABLE}/old.parquet", parquet_bytes(old_columns, rows[:1]))
    index = Index(store)
    _, got = query(index, "SELECT id, peak_force_n FROM episodes")
    assert got == [("old-1", None)] and index.skipped == []
    store.put_once(f"{INDEX}/{EPISODES_TABLE}/new.parquet", parquet_bytes(EPISODE_COLUMNS, rows[1:]))
    index = Index(store)
    _, got = query(index, "SELECT id, peak_force_n FROM episodes ORDER BY id")
    assert got == [("new-1", 12.5), ("old-1", None)] and index.skipped == []
    compact(store)
    _, got = query(Index(store), "SELECT id, peak_force_n FROM episodes ORDER BY id")
    assert got == [("new-1", 12.5), ("old-1", None)]


def _wait_for(cond, timeout_s: float, why) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, why()
        time.sleep(0.1)




def docs_queries() -> list[str]:
    """docs/fleet.md's ten example queries, as written there."""
    import re
    from tests.conftest import ROOT
    text = (ROOT / "docs" / "fleet.md").read_text()
    block = text[text.index("## Ten example queries"):]
    block = block[block.index("```sql") + len("```sql"):]
    block = block[:block.index("```")]
    queries = [q.strip() for q in re.split(r"^-- .*$", block, flags=re.M) if q.strip()]
    assert len(queries) == 10
    return queries


@pytest.mark.slow
def test_the_ten_example_queries_of_the_docs_run(tmp_path, recordings):
    rec = fresh_copy(recordings, tmp_path / "rec")
    store = EpisodeStore(StoreParams(url=f"file://{tmp_path}/store"))
    for f in rec.glob("*.npz"):
        upload(store, f, robot=ROBOT, mcap=False)
    answers = [query(Index(store), q) for q in docs_queries()]
    assert answers[0][1] == [(ROBOT, EPISODES, EPISODES)]


def _run_to_its_end(d, verb: str, params: dict, cancel_after_s: float | None = None) -> dict:
    """`verb` once the arm has braked from the last task (a stop still running refuses it), to its end event."""
    deadline = time.monotonic() + UPLOAD_WAIT_S
    while d.client.command("status")["state"]["mode"] == "busy":
        assert time.monotonic() < deadline, d.log()[-2000:]
        time.sleep(0.1)
    reply = d.client.command(verb, params)
    assert reply["ok"] is True, reply
    if cancel_after_s is not None:
        time.sleep(cancel_after_s)
        assert d.client.command("cancel", {"task": reply["task"]})["ok"] is True
    return d.client.wait_event(("task_done", "task_failed"), reply["task"], 90.0)


@pytest.mark.slow
def test_the_ten_example_queries_answer_on_a_daemons_own_recordings(make_daemon, tmp_path):
    """Issue 50 item 13: on the daemon's own runs three of the ten answered usefully (result was plain
    `failed`, converged_after_s and the latest onsets were null, the workspace box held nothing). A rotate
    (commanded onset, truth from the simulator), an approach (an onset the trigger detected) and a probe
    cancelled under way, each recorded and uploaded by the daemon: each query answers with rows that say
    something."""
    from tests.conftest import rotate_on_the_cutter
    store_dir = tmp_path / "store"
    d = make_daemon(**{"store": {"url": f"file://{store_dir}"}, "record.enabled": True})
    rotate_on_the_cutter(d)
    assert _run_to_its_end(d, "approach", {"direction": [0.0, 0.0, -1.0]})["kind"] == "task_done"
    failed = _run_to_its_end(d, "probe", {}, cancel_after_s=0.5)
    assert failed["kind"] == "task_failed" and failed["error"] == "cancelled", failed
    uploaded = {d.client.wait_event(("episode_uploaded",), None, UPLOAD_WAIT_S)["id"] for _ in range(3)}
    assert len(uploaded) == 3, uploaded
    (q1, q2, q3, q4, q5, q6, q7, q8, q9, q10) = [query(Index(EpisodeStore(StoreParams(url=f"file://{store_dir}"))),
                                                        q)[1] for q in docs_queries()]
    assert q1 == [("sim", 3, 3)], q1
    assert [(r[0], r[2], r[3]) for r in q2] == [("sim", 2.0, 3)], q2                   # eta from the config
    assert all(r[2] is None or r[2] >= 2.0 for r in q3), q3
    assert q4 == [("sim", "probe", "failed: cancelled", 1)], q4
    assert len(q5) == 1 and q5[0][1] is not None and 0.0 < q5[0][1] < 1000.0, q5       # settled within a second
    assert len(q6) == 1 and q6[0][0] == "ekf" and q6[0][1] is not None, q6
    assert len(q7) == 1 and q7[0][2] == 3, q7                                           # one daemon, one config
    assert len(q8) == 3, q8                                                              # the cutter's, in the box
    assert len(q9) == 1 and q9[0][2] > 0.0, q9
    assert len(q10) >= 1 and all(r[1] is not None and r[1] > 0.0 for r in q10), q10   # the approach's, detected


def test_a_recordings_robot_is_held_to_robot_names_rule(tmp_path, recordings):
    """Issue 50 item 6: meta.robot `a/b` became the robot `a/b` in the index (and two segments of its keys)."""
    from tecdard.recording.format import RecordingError, load_recording, save_recording
    src = sorted(fresh_copy(recordings, tmp_path / "rec").glob("*.npz"))[0]
    rec = load_recording(src)
    for bad in ("a/b", "../up", "", "x" * 65, "ünïcode"):
        rec.meta = {**rec.meta, "robot": bad}
        path = tmp_path / "bad.npz"
        save_recording(path, rec)
        if bad:
            with pytest.raises(RecordingError, match="meta.robot: .* give --robot"):
                read_episode(path)
        assert read_episode(path, robot="arm-1").robot == "arm-1"        # named by hand, it goes


def test_the_index_says_how_a_task_failed_when_its_onset_was_commanded_and_when_it_settled(tmp_path):
    """Issue 50 item 13: `result` was plain `failed` (the daemon sends `error` as a string), `detect_latency_s`
    0 for commanded onsets, `converged_after_s` null on every contact of the flagship rotate (its one-sigma
    never falls under 5 mm radially), and a query on a store that does not exist printed 0."""
    import numpy as np
    from tecdard.fleet import episodes as E
    failed = {"kind": "task_failed", "task": "t1", "error": "protective stop (imu_stale): no IMU sample for 60 ms"}
    assert E._result([failed], "t1") == "failed: protective stop (imu_stale)"
    assert E._result([{"kind": "task_failed", "task": "t1", "error": {"code": "fault"}}], "t1") == "failed: fault"
    assert E._result([{"kind": "task_failed", "task": "t1"}], "t1") == "failed"
    t = np.linspace(0.0, 0.3, 31)
    # an estimate that moves in, then stays within 2 mm of its end; its radial one-sigma 6 mm, the hinge axis 0.5 m
    x = 0.157 + 0.05 * np.exp(-t / 0.02)
    ests = np.column_stack([t, x, np.zeros_like(t), np.full_like(t, 0.487), np.full_like(t, 0.0065),
                            np.full_like(t, 0.5), np.full_like(t, 0.004)])
    rows = E._contacts([{"kind": "contact_onset", "t": 0.0, "detected_t": 0.0, "commanded": True}], ests, {}, 0.0)
    assert rows[0]["detect_latency_s"] is None
    settled = rows[0]["converged_after_s"]
    assert settled is not None and abs(x[int(round(settled / 0.01))] - x[-1]) <= 0.005 < abs(x[0] - x[-1])
    rows = E._contacts([{"kind": "contact_onset", "t": 0.0, "detected_t": 0.004}], ests, {}, 0.0)
    assert rows[0]["detect_latency_s"] == pytest.approx(0.004)
    with pytest.raises(StoreError, match="no such directory"):
        EpisodeStore(StoreParams(url=f"file://{tmp_path}/nothing-here"), create=False)
    assert not (tmp_path / "nothing-here").exists()
    res = tecdard("episodes", "query", "SELECT count(*) FROM episodes", "--store", f"file://{tmp_path}/nothing-here")
    assert res.returncode != 0 and "no such directory" in res.stderr and len(res.stderr.strip().splitlines()) == 1
