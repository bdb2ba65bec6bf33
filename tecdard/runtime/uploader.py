"""The daemon's uploader thread: each recording written goes to the fleet's episode store (tecdard.fleet.episodes),
with back-off while the store is away, and what a crash or an outage left behind is found again at start.

It never holds up the estimator, the recorder or the control tick: the recorder's `recording_written`
event reaches it through a bounded queue (a full queue is only a rescan later), it runs at a lower CPU
priority than the daemon's other threads, and every store call is its own."""
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


class Uploader:
    """`submit(path)` from any thread (never blocks); `run(stop)` on the uploader's own thread;
    `may_delete(path)` for the recorder: a recording goes only once the store has it."""

    def __init__(self, params: StoreParams, directory: str, robot: str, emit, config: str | None = None,
                 own_name=None):
        """`emit(kind, **fields)`: an event (episode_uploaded, upload_failed). `own_name`: the pattern of
        the daemon's own recordings' names (recorder.OWN_NAME), for the scan at start."""
        self.params, self.directory, self.robot = params, pathlib.Path(directory), robot
        self.emit, self.config, self.own_name = emit, config, own_name
        self.inbox: queue.Queue = queue.Queue(maxsize=INBOX)
        self.pending: list[pathlib.Path] = []        # owned by the uploader's thread
        self.uploaded = 0
        self.failures = 0
        self._rescan = threading.Event()
        self._rescan.set()                           # at start: what an earlier run left
        self._store: EpisodeStore | None = None

    def submit(self, path: str) -> None:
        try:
            self.inbox.put_nowait(pathlib.Path(path))
        except queue.Full:
            self._rescan.set()

    @staticmethod
    def may_delete(path: pathlib.Path) -> bool:
        return is_uploaded(path)

    def run(self, stop: threading.Event) -> None:
        _lower_priority()
        retry_s, next_try, next_scan = RETRY_FIRST_S, 0.0, time.monotonic() + RESCAN_S
        while not stop.is_set():
            try:
                self._add(self.inbox.get(timeout=0.5))
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
                retry_s, next_try = RETRY_FIRST_S, 0.0

    def _add(self, path: pathlib.Path) -> None:
        if path not in self.pending and path.exists() and not is_uploaded(path):
            self.pending.append(path)

    def _scan(self) -> list[pathlib.Path]:
        """The daemon's own recordings not yet uploaded, oldest first."""
        try:
            files = [f for f in self.directory.iterdir() if self.own_name is None or self.own_name.match(f.name)]
        except OSError:
            return []
        return sorted((f for f in files if f.suffix == ".npz" and not is_uploaded(f)), key=_mtime)

    def _upload(self, path: pathlib.Path) -> None:
        if self._store is None:
            self._store = EpisodeStore(self.params)
        t0 = time.monotonic()
        ep = upload(self._store, path, robot=self.robot, mcap=self.params.mcap, config=self.config)
        self.uploaded += 1
        log.info("recording %s uploaded to %s/%s (%.1f s)", path.name, self._store.url, ep.key(".npz"),
                 time.monotonic() - t0)
        self.emit("episode_uploaded", file=path.name, id=ep.id, key=ep.key(".npz"), store=self._store.url)


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
