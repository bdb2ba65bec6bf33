"""The fleet's episode store: each finished recording in object storage (obstore: the local file system or any
S3 service) at <robot>/<yyyy-mm-dd>/<episode>.npz (and .mcap), and its rows in a Parquet index beside it, one
file per episode (index/episodes/..., index/contacts/...) so that writers never share a file.

Guarantees (docs/fleet.md, "The store"):
- every object is written once, whole (a create-only put): a retried upload finds it there and does not
  write a second copy; an object of the same name but another size is a conflict, never overwritten;
- the index rows go up after the recording, so a row always names an object that is there;
- a local recording is marked uploaded (a `.uploaded` file beside it) only once the store has all of it,
  and the recorder deletes no unmarked recording while a store is configured."""
from __future__ import annotations

import datetime
import json
import logging
import math
import os
import pathlib
import tempfile
from dataclasses import dataclass

import numpy as np

from tecdard.options import option, read_options
from tecdard.safejson import first_line, show

log = logging.getLogger("tecdar.episodes")

INDEX = "index"
EPISODES_TABLE, CONTACTS_TABLE = "episodes", "contacts"
UPLOADED_SUFFIX = ".uploaded"       # beside a local recording: the store has it (JSON: where, when)
SCHEMES = ("file", "s3")
CONVERGED_SIGMA_M = 0.005           # a contact's estimate has settled once it stays this close to its last (5 mm)
UNOBSERVED_STD_M = 0.5              # what the estimator reports along a direction it cannot see (not a sigma)
MAX_INDEX_FILE_BYTES = 64 << 20     # an index file larger than this is no index of ours

EPISODE_COLUMNS = (
    ("id", "VARCHAR"), ("robot", "VARCHAR"), ("episode", "VARCHAR"), ("start_time", "TIMESTAMPTZ"),
    ("day", "DATE"), ("task", "VARCHAR"), ("verb", "VARCHAR"), ("reason", "VARCHAR"), ("backend", "VARCHAR"),
    ("model", "VARCHAR"), ("estimator", "VARCHAR"), ("config_digest", "VARCHAR"), ("eta", "DOUBLE"),
    ("grip_force_n", "DOUBLE"), ("duration_s", "DOUBLE"), ("result", "VARCHAR"), ("contacts", "INTEGER"),
    ("npz_key", "VARCHAR"), ("mcap_key", "VARCHAR"), ("bytes", "BIGINT"), ("uploaded_at", "TIMESTAMPTZ"),
    ("version", "VARCHAR"), ("peak_force_n", "DOUBLE"))
# columns added after the first index files were written: an older file reads them as NULL (fleet/index.py)
LATER_COLUMNS = frozenset({"peak_force_n"})
CONTACT_COLUMNS = (
    ("id", "VARCHAR"), ("robot", "VARCHAR"), ("episode", "VARCHAR"), ("n", "INTEGER"), ("onset_t", "DOUBLE"),
    ("onset_time", "TIMESTAMPTZ"), ("detect_latency_s", "DOUBLE"), ("x_m", "DOUBLE"), ("y_m", "DOUBLE"),
    ("z_m", "DOUBLE"), ("sigma_m", "DOUBLE"), ("std_x_m", "DOUBLE"), ("std_y_m", "DOUBLE"), ("std_z_m", "DOUBLE"),
    ("converged_after_s", "DOUBLE"), ("error_m", "DOUBLE"), ("uploaded_at", "TIMESTAMPTZ"))


class StoreError(RuntimeError):
    """The store refused or could not be reached; the message is one line."""


class Conflict(StoreError):
    """An object of that name is there already and differs: never overwritten."""


@dataclass(frozen=True)
class StoreParams:
    """The `store` section: where episodes go (url: file:///... or s3://bucket/prefix; "" none), an S3
    service's endpoint (MinIO, Ceph; "" AWS), its region, plain HTTP (a lab's MinIO without TLS), whether
    the daemon uploads (its uploader thread) and adds an MCAP beside each recording. Credentials come
    from the environment (AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY: the unit's EnvironmentFile=)."""
    url: str = option("", "where episodes go: file:///srv/tecdar/episodes or s3://bucket/prefix; \"\": none",
                      max_len=1024)
    endpoint: str = option("", "an S3-compatible service's URL (MinIO, Ceph); \"\": AWS", max_len=1024)
    region: str = option("", "the S3 region", max_len=64)
    allow_http: bool = option(False, "plain HTTP to the endpoint (a lab's MinIO without TLS)")
    upload: bool = option(True, "the daemon uploads each recording written (with a url); `tecdard episodes sync` "
                                "uploads by hand")
    mcap: bool = option(True, "an MCAP beside each recording (tecdard export's)")
    retry_max_s: float = option(60.0, "back-off while the store is away, from 1 s doubling to this", unit="s",
                                minval=1.0, maxval=3600.0)

    @classmethod
    def from_config(cls, section) -> "StoreParams":
        params = read_options(cls, section)
        problem = url_problem(params.url) if params.url else None
        if problem:
            raise section.error("url", problem)
        return params


def url_problem(url: str) -> str | None:
    """Why `url` is no store URL we take, or None."""
    scheme, sep, rest = url.partition("://")
    if not sep or scheme not in SCHEMES:
        return f"{show(url)}: expected file:///<directory> or s3://<bucket>[/<prefix>]"
    if scheme == "file" and not rest.startswith("/"):
        return f"{show(url)}: a file:// URL names an absolute directory (file:///srv/tecdar/episodes)"
    if scheme == "s3" and not rest.split("/")[0]:
        return f"{show(url)}: no bucket"
    return None


class EpisodeStore:
    """One object store (obstore) holding the fleet's episodes and their index."""

    def __init__(self, params: StoreParams, create: bool = True):
        """`create` False (a query, a fetch, a compaction): a file:// store's directory must exist already."""
        from obstore.store import from_url
        problem = url_problem(params.url)
        if problem:
            raise StoreError(problem)
        self.url = params.url.rstrip("/")
        self.params = params
        self.bad_keys: list[str] = []       # keys the store's client refused to name, left out of listings
        if not create and self.url.startswith("file://") and not pathlib.Path(self.url.removeprefix("file://")).is_dir():
            raise StoreError(f"store {show(self.url)}: no such directory (nothing was ever uploaded there)")
        try:
            if self.url.startswith("file://"):
                pathlib.Path(self.url.removeprefix("file://")).mkdir(parents=True, exist_ok=True)
                self.store = from_url(self.url + "/")
            else:
                config = {k: v for k, v in (("endpoint", params.endpoint), ("region", params.region)) if v}
                self.store = from_url(self.url, config=config or None,
                                      client_options={"allow_http": True} if params.allow_http else None)
        except (OSError, ValueError, Exception) as exc:
            raise StoreError(f"store {show(self.url)}: {first_line(exc)}") from None

    @property
    def local_root(self) -> pathlib.Path | None:
        """The directory of a file:// store (DuckDB reads its index in place), None for S3."""
        return pathlib.Path(self.url.removeprefix("file://")) if self.url.startswith("file://") else None

    def put_once(self, key: str, data: bytes) -> bool:
        """Write `key` if it is not there: True if written now, False if it was there already with the
        same size (an earlier try got it through); Conflict if it differs, StoreError if the store fails."""
        import obstore
        from obstore.exceptions import AlreadyExistsError
        try:
            obstore.put(self.store, key, data, mode="create")
            return True
        except AlreadyExistsError:
            pass
        except Exception as exc:
            raise StoreError(f"{key}: {first_line(exc)}") from None
        size = self.size(key)
        if size != len(data):
            raise Conflict(f"{key}: already in the store with {size} bytes, not these {len(data)}: left as it is")
        return False

    def size(self, key: str) -> int | None:
        import obstore
        from obstore.exceptions import NotFoundError
        try:
            return int(obstore.head(self.store, key)["size"])
        except (NotFoundError, FileNotFoundError):       # obstore raises the latter for a missing object
            return None
        except Exception as exc:
            raise StoreError(f"{key}: {first_line(exc)}") from None

    def get(self, key: str) -> bytes:
        import obstore
        from obstore.exceptions import NotFoundError
        try:
            return bytes(obstore.get(self.store, key).bytes())
        except (NotFoundError, FileNotFoundError):
            raise StoreError(f"{key}: not in the store") from None
        except Exception as exc:
            raise StoreError(f"{key}: {first_line(exc)}") from None

    def list(self, prefix: str) -> list[dict]:
        """Every object under `prefix`: {path, size, last_modified}. A key obstore refuses to name (a `..`, `.` or
        empty segment, which S3 allows) is left out and kept in `bad_keys`; the rest are listed through
        botocore (fleet/listing.py)."""
        import obstore

        from tecdard.fleet.listing import ListingError, list_raw, refused_key
        try:
            return [m for batch in obstore.list(self.store, prefix=prefix) for m in batch]
        except Exception as exc:
            if self.local_root is not None or refused_key(exc) is None:
                raise StoreError(f"{prefix}: {first_line(exc)}") from None
        p = self.params
        try:
            return list_raw(self.url, p.endpoint, p.region, p.allow_http, prefix, self.bad_keys)
        except ListingError as exc:
            raise StoreError(f"{prefix}: {exc}") from None

    def delete(self, key: str) -> None:
        import obstore
        try:
            obstore.delete(self.store, key)
        except Exception as exc:
            raise StoreError(f"{key}: {first_line(exc)}") from None


# -- an episode's rows ---------------------------------------------------------------------------------

@dataclass
class Episode:
    """A recording as the store files it: its keys, and its index rows."""
    robot: str
    name: str                 # the recording's file name without .npz
    day: str                  # yyyy-mm-dd of its start (UTC)
    row: dict
    contacts: list

    @property
    def id(self) -> str:
        return f"{self.robot}/{self.name}"

    def key(self, ext: str) -> str:
        return f"{self.robot}/{self.day}/{self.name}{ext}"


def read_episode(path: pathlib.Path, robot: str | None = None) -> Episode:
    """The index rows of a recording (RecordingError, one line, for a malformed file): from its meta,
    the live estimates and events a daemon recording carries, or its truth where a simulated one has it."""
    from tecdard.recording.format import RecordingError, load_recording, load_truth
    from tecdard.recording.live import load_live
    rec = load_recording(path)
    live = load_live(path, rec)
    meta = rec.meta or {}
    robot = robot or str(meta.get("robot") or "unknown")
    from tecdard.fleet.roster import name_problem
    problem = name_problem(robot) or (None if robot.replace("_", "").replace("-", "").isalnum() else
                                      f"{show(robot)}: letters, digits, '-' or '_' only")
    if problem is not None:     # it becomes a key's first segment and the index's robot: robot.name's rule
        raise RecordingError(f"meta.robot: {problem} (a robot's name, as robot.name; give --robot)")
    wall = ((meta.get("clock") or {}).get("wall_minus_monotonic_s"))
    t0 = float(rec.imu_t[0])
    start = (t0 + float(wall)) if isinstance(wall, (int, float)) and math.isfinite(wall) else path.stat().st_mtime
    start_dt = datetime.datetime.fromtimestamp(start, datetime.timezone.utc)
    if live is not None:
        events, ests = live.events, live.est
    else:                   # not a daemon's: its contacts as `tecdard localize` finds them
        events, ests = _replayed(path)
    try:
        truth = load_truth(path)
    except RecordingError:
        truth = {}
    result = _result(events, meta.get("task"))
    contacts = _contacts(events, ests, truth, start - t0)
    row = {"robot": robot, "episode": path.stem, "start_time": start_dt, "day": start_dt.date(),
           "task": meta.get("task"), "verb": meta.get("verb"), "reason": meta.get("reason"),
           "backend": meta.get("backend"), "model": meta.get("model"), "estimator": meta.get("estimator"),
           "config_digest": meta.get("config_digest"), "eta": _num(meta.get("eta")),
           "grip_force_n": _num(meta.get("grip_force")), "duration_s": float(rec.imu_t[-1] - rec.imu_t[0]),
           "result": result, "contacts": len(contacts), "version": meta.get("version"),
           "peak_force_n": _peak_force(live)}
    return Episode(robot, path.stem, start_dt.date().isoformat(), row, contacts)


def _replayed(path: pathlib.Path) -> tuple[list, np.ndarray]:
    """(events, estimates (k, 7): t, p, std) of a replay of a recording with no live log."""
    from tecdard.recording.format import RecordingError
    from tecdard.recording.replay import ReplayError, open_replay, replay
    events: list = []
    try:
        r = open_replay(path, ignore_live=True)
    except ReplayError as exc:
        raise RecordingError(str(exc)) from None
    rows, _, _ = replay(r.rec, r.pipeline, on_event=events.append)
    return events, rows


def _peak_force(live) -> float | None:
    """The largest force (N) the arm's own estimate at the TCP reached in the episode (`tcp_wrench`), None
    where the recording has none."""
    w = None if live is None else live.wrench
    if w is None:
        return None
    f = np.linalg.norm(w[:, :3], axis=1)
    f = f[np.isfinite(f)]
    return round(float(f.max()), 3) if len(f) else None


def _num(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _result(events: list, task) -> str | None:
    """How the episode's task ended: done, failed (its code), or None (no task, or not seen)."""
    for ev in reversed(events):
        if not isinstance(ev, dict) or (task is not None and ev.get("task") not in (None, task)):
            continue
        if ev.get("kind") == "task_done":
            return "done"
        if ev.get("kind") == "task_failed":
            return f"failed: {_cause(ev)}" if _cause(ev) else "failed"
    return None


def _cause(ev: dict) -> str | None:
    """How a task failed, in a few words: its code where the event has one, else its error's text up to the
    first ':' (the daemon's `error` is a one-line string: "protective stop: imu_stale ...", "max_distance: ...")."""
    err = ev.get("error")
    if isinstance(err, dict):
        err = err.get("code")
    code = ev.get("code") or ev.get("cause") or err
    if not isinstance(code, str) or not code.strip():
        return None
    return code.split(":")[0].strip()[:60]


def _contacts(events: list, ests: np.ndarray, truth: dict, wall_offset_s: float) -> list[dict]:
    """One row per contact onset: the last estimate before the next onset, its one-sigma (the largest
    standard deviation along the directions observed: an edge's or hinge's own axis is not), when the
    estimate settled (_settled_after), and the error against a truth (the simulator's hinge
    in the task's result, or a simulated recording's contact point)."""
    # a daemon recording holds an onset both as its estimator passed it and as the daemon published it
    onsets = list({float(ev["t"]): ev for ev in events if isinstance(ev, dict) and ev.get("kind") == "contact_onset"
                   and isinstance(ev.get("t"), (int, float))}.values())
    onsets.sort(key=lambda ev: float(ev["t"]))
    truth_line = _truth_line(events, truth)
    rows = []
    for n, ev in enumerate(onsets):
        t_on = float(ev["t"])
        t_next = float(onsets[n + 1]["t"]) if n + 1 < len(onsets) else math.inf
        mine = ests[(ests[:, 0] >= t_on) & (ests[:, 0] < t_next)] if len(ests) else ests
        row = {"n": n, "onset_t": t_on,
               "onset_time": datetime.datetime.fromtimestamp(t_on + wall_offset_s, datetime.timezone.utc),
               # a commanded onset (a task that starts its own episode) detected nothing: no latency
               "detect_latency_s": _num(ev.get("detected_t", math.nan) - t_on) if isinstance(
                   ev.get("detected_t"), (int, float)) and not ev.get("commanded") else None,
               "x_m": None, "y_m": None, "z_m": None, "sigma_m": None, "std_x_m": None, "std_y_m": None,
               "std_z_m": None, "converged_after_s": None, "error_m": None}
        if len(mine):
            sig = np.array([_sigma(r[4:7]) for r in mine])
            last = mine[-1]
            row.update(x_m=float(last[1]), y_m=float(last[2]), z_m=float(last[3]), sigma_m=_num(sig[-1]),
                       std_x_m=float(last[4]), std_y_m=float(last[5]), std_z_m=float(last[6]))
            row["converged_after_s"] = _settled_after(mine, t_on)
            if truth_line is not None:
                point, axis = truth_line
                d = last[1:4] - point
                if axis is not None:
                    d = d - float(d @ axis) * axis
                row["error_m"] = float(np.linalg.norm(d))
        rows.append(row)
    return rows


def _settled_after(ests: np.ndarray, t_on: float) -> float | None:
    """When the estimate came, and stayed, within CONVERGED_SIGMA_M of where it ended, along the directions
    it observes (an edge's or hinge's own axis it cannot see, and its reported one-sigma there is a placeholder):
    the contact's in-plane error against its own final answer, which needs no truth. None: it never settled
    (the episode's last estimate alone, or it moved to the end)."""
    final, observed = ests[-1, 1:4], ests[-1, 4:7] < 0.5 * UNOBSERVED_STD_M
    if len(ests) < 2 or not observed.any():
        return None
    far = np.linalg.norm((ests[:, 1:4] - final)[:, observed], axis=1) > CONVERGED_SIGMA_M
    last_far = np.flatnonzero(far)
    k = 0 if not len(last_far) else int(last_far[-1]) + 1
    return None if k >= len(ests) - 1 else float(ests[k, 0] - t_on)


def _sigma(std: np.ndarray) -> float:
    seen = std[std < 0.5 * UNOBSERVED_STD_M]
    return float(seen.max()) if len(seen) else float("nan")


def _truth_line(events: list, truth: dict):
    """(a point, a unit axis or None) of the true contact: the simulator's hinge from a task's result,
    else a simulated recording's truth_p_c (and truth_axis)."""
    for ev in reversed(events):
        sim = ((ev.get("result") or {}).get("sim") if isinstance(ev, dict) and isinstance(ev.get("result"), dict)
               else None)
        if isinstance(sim, dict) and np.shape(sim.get("hinge_point")) == (3,):
            axis = np.asarray(sim.get("hinge_axis"), float) if np.shape(sim.get("hinge_axis")) == (3,) else None
            return np.asarray(sim["hinge_point"], float), (None if axis is None else axis / np.linalg.norm(axis))
    p = truth.get("p_c")
    if p is not None and np.shape(p) == (3,):
        axis = truth.get("axis")
        axis = np.asarray(axis, float) if np.shape(axis) == (3,) and np.linalg.norm(axis) > 0 else None
        return np.asarray(p, float), (None if axis is None else axis / np.linalg.norm(axis))
    return None


def parquet_bytes(columns: tuple, rows: list[dict]) -> bytes:
    """rows as one Parquet file (DuckDB writes it), the columns typed as given."""
    import duckdb
    with tempfile.TemporaryDirectory(prefix="tecdar-index-") as tmp:
        out = pathlib.Path(tmp) / "rows.parquet"
        con = duckdb.connect()
        try:
            con.execute("CREATE TABLE t (" + ", ".join(f'"{n}" {t}' for n, t in columns) + ")")
            if rows:
                con.executemany("INSERT INTO t VALUES (" + ", ".join("?" for _ in columns) + ")",
                                [[r.get(n) for n, _ in columns] for r in rows])
            con.execute(f"COPY t TO '{out}' (FORMAT parquet)")
        finally:
            con.close()
        return out.read_bytes()


# -- upload --------------------------------------------------------------------------------------------

def upload(store: EpisodeStore, path: pathlib.Path, robot: str | None = None, mcap: bool = True,
           config: str | None = None) -> Episode:
    """Put a recording, its MCAP (when foxglove-sdk is here and `mcap`), then its index rows into the
    store, each at most once; then mark the local file uploaded. Idempotent: run again after any failure
    it completes what is missing and never writes a second copy."""
    ep = read_episode(path, robot)
    data = path.read_bytes()
    uploaded_at = datetime.datetime.now(datetime.timezone.utc)
    store.put_once(ep.key(".npz"), data)
    mcap_key = None
    if mcap:
        blob = _mcap_bytes(path, config)
        if blob is not None:
            mcap_key = ep.key(".mcap")
            if store.size(mcap_key) is None:
                store.put_once(mcap_key, blob)
    row = {**ep.row, "id": ep.id, "npz_key": ep.key(".npz"), "mcap_key": mcap_key, "bytes": len(data),
           "uploaded_at": uploaded_at}
    contacts = [{**c, "id": ep.id, "robot": ep.robot, "episode": ep.name, "uploaded_at": uploaded_at}
                for c in ep.contacts]
    # an index row written once: a retry after a failure between the two files finds the first there
    for table, columns, rows in ((CONTACTS_TABLE, CONTACT_COLUMNS, contacts), (EPISODES_TABLE, EPISODE_COLUMNS, [row])):
        key = index_key(table, ep)
        if store.size(key) is None:
            store.put_once(key, parquet_bytes(columns, rows))
    mark_uploaded(path, store.url, ep)
    return ep


def index_key(table: str, ep: Episode) -> str:
    return f"{INDEX}/{table}/{ep.robot}/{ep.name}.parquet"


def _mcap_bytes(path: pathlib.Path, config: str | None) -> bytes | None:
    """The recording as MCAP (tecdard export's, the estimator tuned by `config`), or None without
    foxglove-sdk (the viz extra)."""
    try:
        import foxglove  # noqa: F401
    except ImportError:
        return None
    from tecdard.recording.mcap import export_mcap
    with tempfile.TemporaryDirectory(prefix="tecdar-mcap-") as tmp:
        out = pathlib.Path(tmp) / (path.stem + ".mcap")
        try:
            export_mcap(path, out, config)
        except Exception as exc:         # the MCAP is a convenience: its failure never holds the recording back
            log.warning("%s: no MCAP (%s)", path.name, first_line(exc))
            return None
        return out.read_bytes()


def marker(path: pathlib.Path) -> pathlib.Path:
    return path.with_name(path.name + UPLOADED_SUFFIX)


def mark_uploaded(path: pathlib.Path, url: str, ep: Episode) -> None:
    """Add `url` to the stores the marker beside `path` names (written whole, then moved into place)."""
    entries = [e for e in _marker_entries(path) if e.get("store") != url.rstrip("/")]
    entries.append({"store": url.rstrip("/"), "key": ep.key(".npz"),
                    "at": datetime.datetime.now(datetime.timezone.utc).isoformat()})
    tmp = marker(path).with_suffix(".tmp")
    tmp.write_text(json.dumps({"stores": entries}) + "\n")
    os.replace(tmp, marker(path))


def _marker_entries(path: pathlib.Path) -> list[dict]:
    """The stores the marker says have the recording: `{"stores": [{store, key, at}, ...]}`, or an older
    marker's one `{store, key, at}`; none for a marker that is missing or unreadable (then the recording is
    kept and uploaded again: an upload never writes an object twice)."""
    try:
        data = json.loads(marker(path).read_text())
    except (OSError, ValueError):
        return []
    entries = data.get("stores") if isinstance(data, dict) and "stores" in data else [data]
    return [e for e in entries if isinstance(e, dict) and isinstance(e.get("store"), str)] \
        if isinstance(entries, list) else []


def is_uploaded(path: pathlib.Path, url: str) -> bool:
    """Whether the store at `url` has the recording (a marker names each store that has it: one store's copy
    never counts for another)."""
    return any(e["store"] == url.rstrip("/") for e in _marker_entries(path))
