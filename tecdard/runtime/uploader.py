"""The daemon's uploader thread: each recording written goes to the fleet's episode store (tecdard.fleet.episodes),
with back-off while the store is away, and what a crash or an outage left behind is found again at start.

It never holds up the estimator, the recorder or the control tick: the recorder's `recording_written`
event reaches it through a bounded queue (a full queue is only a rescan later); the work itself (reading
the recording, the MCAP's replay, DuckDB, the store's client) runs in a process of its own at nice +10,
so it never holds the daemon's GIL (in the daemon's own thread, an upload with its MCAP held the tick
up to 20 ms: 7 overruns in 12 uploads); and an upload starts only while no task runs."""
from __future__ import annotations

import logging
import os
import pathlib
import queue
import threading
import time

from tecdard.fleet.episodes import Conflict, EpisodeStore, StoreError, StoreParams, is_uploaded, upload

log = logging.getLogger("tecdar.upload")

INBOX = 256                    # recordings written and not yet taken by the uploader
RETRY_FIRST_S = 1.0            # the first retry after a failure; doubled up to store.retry_max_s
UPLOADER_NICE = 10             # how much nicer than the daemon's threads the uploader runs
RESCAN_S = 300.0               # the recordings directory is looked through again this often
IDLE_WAIT_S = 0.5              # with nothing due, the uploader waits this long for a new recording
DUTY = 0.5                     # a backlog is uploaded at most this fraction of the time (the rest, a pause)
WORKER_TIMEOUT_S = 600.0       # one upload (a recording of at most 120 s, its MCAP) takes no longer than this
WORKER_IDLE_S = 60.0           # the upload process ends after this long without work (its memory back)
WORKER_CLOSE_S = 5.0
WORKER_NAME = "tecdar-upload"


class Uploader:
    """`submit(path)` from any thread (never blocks); `run(stop)` on the uploader's own thread;
    `may_delete(path)` for the recorder: a recording goes only once the store has it."""

    def __init__(self, params: StoreParams, directory: str, robot: str, emit, config: str | None = None,
                 own_name=None, at_rest=None):
        """`emit(kind, **fields)`: an event (episode_uploaded, upload_failed). `own_name`: the pattern of
        the daemon's own recordings' names (recorder.OWN_NAME), for the scan at start. `at_rest()`: False
        while a task runs; no upload starts then (its replay and MCAP would compete with the task's
        threads for the GIL)."""
        self.params, self.directory, self.robot = params, pathlib.Path(directory), robot
        self.emit, self.config, self.own_name = emit, config, own_name
        self.at_rest = at_rest or (lambda: True)
        self.inbox: queue.Queue = queue.Queue(maxsize=INBOX)
        self.pending: list[pathlib.Path] = []        # owned by the uploader's thread
        self.uploaded = 0
        self.failures = 0
        self._rescan = threading.Event()
        self._rescan.set()                           # at start: what an earlier run left
        self._worker: UploadWorker | None = None

    def submit(self, path: str) -> None:
        try:
            self.inbox.put_nowait(pathlib.Path(path))
        except queue.Full:
            self._rescan.set()

    def may_delete(self, path: pathlib.Path) -> bool:
        """The recorder's budget may delete `path` once this daemon's own store has it (a copy in another store,
        an `episodes sync` to a try-out store, does not count)."""
        return is_uploaded(path, self.params.url)

    def run(self, stop: threading.Event) -> None:
        try:
            self._run(stop)
        finally:
            self.close()

    def _run(self, stop: threading.Event) -> None:
        _lower_priority()
        retry_s, next_try, next_scan = RETRY_FIRST_S, 0.0, time.monotonic() + RESCAN_S
        while not stop.is_set():
            # with work due, take what came in without waiting; otherwise wait for it (or the retry)
            wait_s = IDLE_WAIT_S if not self.pending else min(IDLE_WAIT_S, max(next_try - time.monotonic(), 0.0))
            try:
                self._add(self.inbox.get(timeout=wait_s) if wait_s > 0.0 else self.inbox.get_nowait())
            except queue.Empty:
                pass
            now = time.monotonic()
            if self._rescan.is_set() or now >= next_scan:
                self._rescan.clear()
                next_scan = now + RESCAN_S
                for path in self._scan():
                    self._add(path)
            if not self.pending or now < next_try:
                continue
            if not self.at_rest():
                next_try = now + IDLE_WAIT_S
                continue
            path = self.pending[0]
            try:
                self._upload(path)
            except Conflict as exc:
                self.pending.pop(0)
                self.failures += 1
                log.error("recording %s not uploaded: %s", path.name, exc)
                self.emit("upload_failed", file=path.name, message=str(exc), retry=False)
            except (StoreError, OSError, ValueError) as exc:
                # the store away, or a file we cannot read: tried again later (the file stays on disk)
                self.failures += 1
                log.warning("recording %s not uploaded (retry in %.0f s): %s", path.name, retry_s, exc)
                self.emit("upload_failed", file=path.name, message=str(exc)[:300], retry=True, retry_s=retry_s)
                next_try = now + retry_s
                retry_s = min(2.0 * retry_s, self.params.retry_max_s)
                if isinstance(exc, ValueError):        # a malformed recording (RecordingError): never uploadable
                    self.pending.pop(0)
            except Exception:                          # a bug of ours: said, and the thread goes on
                self.pending.pop(0)
                self.failures += 1
                log.exception("recording %s not uploaded", path.name)
            else:
                self.pending.pop(0)
                # a backlog (after an outage) goes up at DUTY of the time, not in one burst
                retry_s, next_try = RETRY_FIRST_S, time.monotonic() + (time.monotonic() - now) * (1.0 / DUTY - 1.0)

    def _add(self, path: pathlib.Path) -> None:
        if path not in self.pending and path.exists() and not is_uploaded(path, self.params.url):
            self.pending.append(path)

    def _scan(self) -> list[pathlib.Path]:
        """The daemon's own recordings not yet uploaded, oldest first."""
        try:
            files = [f for f in self.directory.iterdir() if self.own_name is None or self.own_name.match(f.name)]
        except OSError:
            return []
        return sorted((f for f in files if f.suffix == ".npz" and not is_uploaded(f, self.params.url)), key=_mtime)

    def _upload(self, path: pathlib.Path) -> None:
        if self._worker is None:
            self._worker = UploadWorker(self.params, self.robot, self.config)
        t0 = time.monotonic()
        done = self._worker.upload(path)
        self.uploaded += 1
        log.info("recording %s uploaded to %s/%s (%.1f s)", path.name, done["store"], done["key"],
                 time.monotonic() - t0)
        self.emit("episode_uploaded", file=path.name, id=done["id"], key=done["key"], store=done["store"])

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()


class UploadWorker:
    """The uploads' own process (spawned: never a fork of a process running Zenoh's threads): a path in,
    its outcome back. It ends itself after WORKER_IDLE_S without work and is started again when due; one
    that dies or hangs past WORKER_TIMEOUT_S is killed and its upload counts as a store failure."""

    def __init__(self, params: StoreParams, robot: str, config: str | None):
        self.args = (params, robot, config)
        self._proc = None
        self._conn = None

    def upload(self, path: pathlib.Path) -> dict:
        """{"id", "key", "store"}; Conflict, StoreError or ValueError (a malformed recording) otherwise."""
        for attempt in (0, 1):
            if self._proc is None or not self._proc.is_alive():
                self._start()
            try:
                self._conn.send(str(path))
                if not self._conn.poll(WORKER_TIMEOUT_S):
                    self._kill()
                    raise StoreError(f"the upload did not finish within {WORKER_TIMEOUT_S:.0f} s")
                out = self._conn.recv()
                break
            except (EOFError, BrokenPipeError, ConnectionResetError, OSError):
                self._kill()                  # it ended (idle, or died): once more with a new one
                if attempt:
                    raise StoreError("the upload's process ended without an answer") from None
        kind, value = out
        if kind == "ok":
            return value
        raise {"conflict": Conflict, "bad": ValueError}.get(kind, StoreError)(value)

    def _start(self) -> None:
        import multiprocessing
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        from tecdard.host import without_ctrl_c
        self._proc = ctx.Process(target=without_ctrl_c, args=(_worker_main, child, *self.args), name="tecdar-upload",
                                 daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent

    def _kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.join(5.0)
        self._proc = None

    def close(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            try:
                self._conn.send(None)
            except OSError:
                pass
            self._proc.join(WORKER_CLOSE_S)
        self._kill()


def _worker_main(conn, params: StoreParams, robot: str, config: str | None) -> None:
    """The upload process: nice +10, one store client, until told to end or idle for WORKER_IDLE_S."""
    from tecdard.host import name_os_thread
    name_os_thread(WORKER_NAME)              # `ps` and `top` show it as what it is
    try:
        os.nice(UPLOADER_NICE)
    except OSError:
        pass
    store = None
    while conn.poll(WORKER_IDLE_S):
        path = conn.recv()
        if path is None:
            break
        try:
            store = store or EpisodeStore(params)
            ep = upload(store, pathlib.Path(path), robot=robot, mcap=params.mcap, config=config)
            out = ("ok", {"id": ep.id, "key": ep.key(".npz"), "store": store.url})
        except Conflict as exc:
            out = ("conflict", str(exc))
        except (StoreError, OSError) as exc:
            out = ("store", str(exc)[:500])
        except ValueError as exc:           # RecordingError: a malformed recording
            out = ("bad", str(exc)[:500])
        except Exception as exc:            # a bug of ours: said as a store failure, retried later
            out = ("store", f"{type(exc).__name__}: {exc}"[:500])
        conn.send(out)


def _mtime(path: pathlib.Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _lower_priority() -> None:
    """This thread (Linux: a thread's nice value is its own) at UPLOADER_NICE below the daemon's."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + UPLOADER_NICE)
    except (OSError, AttributeError):
        pass
