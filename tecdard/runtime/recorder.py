"""Live recordings: every contact episode (and captures on demand) as a `tecdar-recording/1` file.

The estimator thread hands the recorder what it fed its pipeline at each pass: the proprioception
samples it added, the directive and data rate in force, the IMU batch, the events and the estimate
that came out. `record.pre_onset_s` of that is kept in a bounded buffer; a contact onset (with
`record.enabled`) or a `record start` command opens a capture that runs until the episode or its
task ends, or `record stop`. The recorder's own thread writes the file (a temporary name, then one
rename); nothing here ever blocks the estimator or the control thread: the hand-over is a bounded
queue whose overflow is dropped and counted.

What is never lost, and what can be:
- Before each write the directory is made room in, as journald's SystemMaxUse= and
  SystemKeepFree= do: the oldest of the daemon's own recordings (by their names, OWN_NAME; no other
  file is ever touched) go until the recordings fit `record.max_mb` and the filesystem keeps
  `record.keep_free_mb` free. A write that would still not fit is refused with a
  `recording_failed` event naming the shortfall, and the older recordings stay.
- A capture still open is written every `record.checkpoint_s` (10 s) to its final name
  (uncompressed: fast), so a daemon killed with SIGKILL loses at most the last 10 s of it (and
  the passes still queued); the file it leaves says so in its meta (`ended`).
- On SIGTERM the daemon closes the capture at once and writes it (uncompressed) while the arm
  stops, well within the unit's stop timeout (docs/recordings.md).
- A full disk or a write error is a logged warning, a `recording_failed` event and a count.

Beyond the format's keys a daemon recording carries what a faithful replay needs (`live_*`, see
docs/recordings.md): each pass's batch boundary, the pass at which each proprioception sample
reached the pipeline, the directives and data rates as they changed, the gyro bias at the start,
and the live estimates and events, so `tecdard localize` reproduces the live answer (runtime/capture.py
builds the file from a capture).
"""
from __future__ import annotations

import collections
import datetime
import errno
import hashlib
import logging
import os
import pathlib
import re
import tempfile
import threading
import time
from dataclasses import dataclass

import numpy as np

from tecdard.api import commands as C
from tecdard.options import option, read_options
from tecdard.runtime.capture import Capture, CaptureCommand, Commanded, EmptyCapture, NotedEvent, Pass, build
from tecdard.runtime.intake import TokenBucket
from tecdard.runtime.messages import Inbox
from tecdard.fleet.episodes import UPLOADED_SUFFIX
from tecdard.files import FILE_MODE, PARTIAL_PREFIX, OutputError, ensure_writable_dir, state_dir
from tecdard.recording.format import save_recording

log = logging.getLogger("tecdar.record")

POLL_S = 0.05                # the recorder takes what its inbox holds this often
QUEUE_STEPS = 4096           # estimator passes waiting for the recorder (about 20 s at 200 passes/s)
MAX_CAPTURE_S = 120.0        # a capture is closed (and written) after this long, whatever is open
LABEL_RE = re.compile(r"[^A-Za-z0-9_.-]+")
MAX_LABEL_CHARS = 40
TASK_END_KINDS = ("task_done", "task_failed")
PRE_EVENTS = 64             # daemon events kept from before a capture (those in its window are written)
PRE_COMMANDS = 600          # control ticks' commands kept from before a capture (12 s at 50 Hz; record.pre_onset_s
                            # is at most 10 s): those from its first IMU sample on are written
TASK_END_GRACE_S = 0.5       # after its episode, a capture waits this long for its task's end event
ADOPT_BEFORE_START_S = 0.05   # an idle capture whose onset is at most this much before a task's start is that task's
CHECKPOINT_S = 10.0          # a capture still open is written this often (what SIGKILL can cost): record.checkpoint_s
# The daemon's own recordings, by name (file_name): <YYYYmmdd-HHMMSS>-<task or idle>[-<label>][~n].npz.
# Only these are ever deleted to make room.
OWN_NAME = re.compile(r"^\d{8}-\d{6}-[A-Za-z0-9_.-]+?(~\d+)?\.npz$")
KEEP_FREE_FRACTION = 0.15    # record.keep_free_mb by default: journald's SystemKeepFree= default,
KEEP_FREE_CAP_MB = 4096.0    # 15 % of the filesystem, at most 4 GiB


def default_dir() -> str:
    return str(state_dir() / "recordings")


@dataclass(frozen=True)
class RecordParams:
    """The `record` config section."""
    enabled: bool = option(False, "every contact episode as a tecdar-recording/1 file (`record` captures on "
                                  "demand either way)")
    dir: str = option(default_dir, "where the recordings go", shown="$STATE_DIRECTORY/recordings under systemd, "
                                                                    "else ~/.local/state/tecdar/recordings")
    pre_onset_s: float = option(1.0, "the buffer kept before an onset (or a `record start`)", unit="s", minval=0.0,
                                maxval=10.0)
    max_mb: float = option(2000.0, "the daemon's own recordings' budget: its oldest go first (each logged)",
                           unit="MB", above=0.0, maxval=1e7)
    keep_free_mb: float | None = option(None, "free space always left on the filesystem; none: 15 % of it, at most "
                                              "4 GiB", unit="MB", kind="optfloat", minval=0.0, maxval=1e7)
    max_on_demand_per_min: float = option(2.0, "captures on demand started per minute, after a burst of "
                                               "max_on_demand_burst (rate_limited beyond)", above=0.0, maxval=600.0)
    max_on_demand_burst: int = option(10, "captures on demand in a row before the per-minute rate holds",
                                      minval=1, maxval=1000)
    checkpoint_s: float = option(CHECKPOINT_S, "an open capture is written this often (what a SIGKILL can cost)",
                                 unit="s", minval=1.0, maxval=MAX_CAPTURE_S)
    max_idle_capture_s: float = option(10.0, "a capture with no task running (an onset at rest) is closed after "
                                             "this", unit="s", minval=0.5, maxval=MAX_CAPTURE_S)

    @classmethod
    def from_config(cls, section) -> "RecordParams":
        params = read_options(cls, section)
        try:
            ensure_writable_dir(params.dir, "dir")
        except OutputError as exc:
            raise section.error("dir", exc.reason) from None
        return params


class Recorder:
    """Fed by the estimator thread (`feed`) and the main thread (`note_event`, `command`); owns its
    capture state on its own thread (`run`). `emit(kind, **fields)` publishes its events."""

    def __init__(self, params: RecordParams, emit, meta: dict):
        self.params = params
        self.emit = emit
        self.meta = meta
        self._inbox = Inbox(QUEUE_STEPS)
        self._taking = False           # the recorder's thread is taking what it drained (idle)
        self.write_failures = 0
        self.may_delete = None         # set before run(): may_delete(path) False keeps that recording (an upload due)
        self._pre: collections.deque = collections.deque()
        self._pre_events: collections.deque = collections.deque(maxlen=PRE_EVENTS)
        self._pre_cmds: collections.deque = collections.deque(maxlen=PRE_COMMANDS)
        self._capture: Capture | None = None
        self._task: tuple[str, str] | None = None       # (id, verb) of the running task
        self._manual: str | None = None                  # main thread: the label of a capture on demand
        # captures on demand started (main thread) and ended (recorder thread: record stop, 120 s, the daemon
        # stopping); all ended: the one the main thread holds has closed by itself, and a start is no longer busy
        self._manual_started = self._manual_ended = 0
        self._starts = TokenBucket(params.max_on_demand_per_min / 60.0, params.max_on_demand_burst)

    # -- hand-over (other threads) -------------------------------------------------
    def feed(self, p: Pass) -> None:
        """On the estimator thread: never blocks; an overflow is dropped and counted."""
        self._inbox.put(p)

    def note_event(self, event: dict) -> None:
        """On the main thread: a daemon event (task starts and ends close captures)."""
        self._inbox.put(NotedEvent(event))

    def note_command(self, t: float, qd) -> None:
        """On the control thread: the tick's commanded joint rates (never blocks; an overflow is dropped)."""
        self._inbox.put(Commanded(t, np.array(qd, dtype=float)))

    def request(self, action: str, label: str) -> dict:
        """On the main thread: a `record` command's reply. The main thread owns whether a capture on
        demand runs (`_manual`); the capture itself is the recorder thread's."""
        if self._manual is not None and self._manual_ended >= self._manual_started:
            self._manual = None                              # it closed by itself (MAX_CAPTURE_S): written
        if action == "start":
            if self._manual is not None:
                raise C.CommandError(C.BUSY, f"record: a capture on demand is running (label "
                                             f"{self._manual!r}); record stop first")
            if not self._starts.take(time.monotonic()):
                p = self.params
                raise C.CommandError(C.RATE_LIMITED, f"record: at most {p.max_on_demand_burst} captures on demand "
                                                     f"in a row, then {p.max_on_demand_per_min:g} a minute "
                                                     "(record.max_on_demand_per_min); try again later")
            self._manual = clean_label(label)
            self._manual_started += 1
            self._inbox.put(CaptureCommand("start", self._manual))
            return {"ok": True, "recording": True, "label": self._manual, "dir": self.params.dir}
        if self._manual is None:
            raise C.CommandError(C.NOT_RECORDING, "record: no capture on demand is running")
        label, self._manual = self._manual, None
        self._inbox.put(CaptureCommand("stop", label))
        return {"ok": True, "recording": False, "label": label}

    def close_capture(self, why: str) -> None:
        """Any thread: close the open capture and write it now, uncompressed (the daemon is stopping:
        the write must end well within the unit's stop timeout)."""
        self._inbox.put(CaptureCommand("close", why))

    @property
    def idle(self) -> bool:
        """Nothing waiting to be taken and no capture open (the daemon may stop without losing one)."""
        return not self._taking and self._capture is None and self._inbox.empty()

    @property
    def dropped_passes(self) -> int:
        """Items lost because the recorder fell behind (counted, never waited for)."""
        return self._inbox.dropped

    # -- the recorder's thread ------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._taking = True              # before the drain: what it takes (or writes) is not idle until done
            items = self._inbox.drain()
            if not items:
                self._check_age()
                self._taking = False
                # what comes meanwhile waits in the inbox (20 s of passes): woken by every pass, this
                # thread was 100-200 wake-ups a second at rest for nothing that is due
                stop.wait(POLL_S)
                continue
            for item in items:
                try:
                    self._take(item)
                except Exception:                    # a bug here costs a recording, never the daemon
                    log.exception("recorder: a %s was lost", type(item).__name__)
                    self._capture = None
            self._taking = False
        if self._capture is not None:            # the daemon stops: what was captured is kept
            try:
                self._write(self._capture, "daemon stopping", compress=False)
            except Exception:
                log.exception("recorder: the capture open at shutdown was lost")

    def _take(self, item) -> None:
        if isinstance(item, Pass):
            self._on_pass(item)
        elif isinstance(item, NotedEvent):
            self._on_event(item.event)
        elif isinstance(item, Commanded):
            if self._capture is not None:
                self._capture.commands.append(item)
            else:
                self._pre_cmds.append(item)
        else:
            self._on_command(item.what, item.arg)
        self._check_age()

    def _on_pass(self, p: Pass) -> None:
        cap = self._capture
        if cap is not None and not cap.manual and cap.task is None and p.directive.episode != cap.episode:
            # an idle capture (no task) whose episode was released, by a task's start or otherwise:
            # closed before this pass, which belongs to what comes next (never a task in an idle file)
            self._finish("the episode ended")
            cap = None
        if cap is not None and not cap.manual and cap.end_by is None and p.directive.episode != cap.episode:
            # the pipeline was released before this pass: its task's end event is on its way (or
            # there is no task): wait for it a little, so that the file holds it
            cap.end_by = time.monotonic() + (TASK_END_GRACE_S if cap.task is not None else 0.0)
        if cap is not None:
            cap.passes.append(p)
        else:
            self._pre.append(p)
            self._trim_pre()
        onset = next((e for e in p.events if e.get("kind") == "contact_onset"), None)
        if self._capture is None and self.params.enabled and onset is not None:
            task, verb = self._task or (None, None)
            self._open("episode", "", task, verb, p.directive.episode)
            t = onset.get("t")
            self._capture.onset_t = float(t) if isinstance(t, (int, float)) else None

    def _on_event(self, ev: dict) -> None:
        kind = ev.get("kind")
        if kind == "task_started":
            self._task = (str(ev.get("task")), str(ev.get("verb")))
            cap = self._capture
            t_start = ev.get("t")
            if (cap is not None and not cap.manual and cap.task is None and cap.onset_t is not None
                    and isinstance(t_start, (int, float)) and cap.onset_t >= t_start - ADOPT_BEFORE_START_S):
                # the task's own onset (a commanded one is dated at its first tick, a hair before its start
                # event), whose pass reached this thread before the start event did: its capture, not an idle one
                cap.task, cap.verb = self._task
            elif cap is not None and not cap.manual and cap.task != self._task[0]:
                self._finish("a task started")          # a task is never filed inside another capture
        cap = self._capture
        if cap is None:
            self._pre_events.append(ev)
        else:
            cap.events.append(ev)
            if kind in TASK_END_KINDS and cap.task == ev.get("task") and not cap.manual:
                self._finish("the task ended")
        if kind in TASK_END_KINDS:
            self._task = None

    def _on_command(self, action: str, label: str) -> None:
        if action == "start":
            if self._capture is not None:
                self._capture.manual, self._capture.label = True, label or self._capture.label
                return
            task, verb = self._task or (None, None)
            episode = self._pre[-1].directive.episode if self._pre else 0
            self._open("manual", label, task, verb, episode, manual=True)
        elif action == "stop" and self._capture is not None:
            self._finish("record stop")
        elif action == "close" and self._capture is not None:
            cap, self._capture = self._capture, None
            self._manual_ended += cap.manual
            self._write(cap, label, compress=False)

    def _open(self, reason: str, label: str, task, verb, episode: int, manual: bool = False) -> None:
        t0 = next((p.t_end for p in self._pre if p.t_end is not None), None)
        events = [e for e in self._pre_events if t0 is not None and isinstance(e.get("t"), (int, float))
                  and e["t"] >= t0 - self.params.pre_onset_s]
        self._capture = Capture(reason, label, task, verb, episode, list(self._pre), events, manual=manual,
                                lost_at_open=self.dropped_passes,
                                commands=[c for c in self._pre_cmds if t0 is not None and c.t >= t0])
        self._pre.clear()
        self._pre_events.clear()
        self._pre_cmds.clear()

    def _trim_pre(self) -> None:
        newest = next((p.t_end for p in reversed(self._pre) if p.t_end is not None), None)
        if newest is None:
            return
        horizon = newest - self.params.pre_onset_s
        while len(self._pre) > 1 and (self._pre[0].t_end is None or self._pre[0].t_end < horizon):
            self._pre.popleft()

    def _check_age(self) -> None:
        cap = self._capture
        now = time.monotonic()
        if cap is not None and cap.end_by is not None and now >= cap.end_by:
            self._finish("the episode ended")
        elif cap is not None and now - cap.t_open > MAX_CAPTURE_S:
            self._finish(f"longer than {MAX_CAPTURE_S:g} s")
        elif (cap is not None and cap.task is None and not cap.manual
              and now - cap.t_open > self.params.max_idle_capture_s):
            # an onset with no task (a bump, the arm's own motion) is not followed for minutes
            self._finish(f"no task, {self.params.max_idle_capture_s:g} s (record.max_idle_capture_s)")
        elif cap is not None and now - cap.saved_at >= self.params.checkpoint_s:
            cap.saved_at = now
            self._write(cap, "", checkpoint=True)

    def _finish(self, why: str) -> None:
        cap, self._capture = self._capture, None
        if cap is not None:
            self._manual_ended += cap.manual
            self._write(cap, why)

    # -- writing --------------------------------------------------------------------
    def _write(self, cap: Capture, why: str, checkpoint: bool = False, compress: bool = True) -> None:
        """Write the capture to its file (a checkpoint: so far, uncompressed, no event), after making
        room for it; a failure is a warning, an event and a count, never an exception."""
        lost = self.dropped_passes - cap.lost_at_open
        ended = ("still open: a checkpoint (the daemon did not close this capture; the last "
                 f"{self.params.checkpoint_s:g} s at most are missing)") if checkpoint else why
        try:
            rec, extra = build(cap, {**self.meta, "ended": ended, "passes_lost": lost})
        except EmptyCapture as exc:
            if not checkpoint:
                log.info("recording not written (%s): %s", why, exc)
            return
        directory = pathlib.Path(self.params.dir)
        path = cap.path or self._new_path(directory, cap)
        need = sum(np.asarray(v).nbytes for v in (rec.imu_t, rec.gyro, rec.accel, rec.tcp_t, rec.tcp_pos,
                                                  rec.tcp_quat, *extra.values()))
        tmp = None
        try:
            directory.mkdir(mode=0o700, parents=True, exist_ok=True)
            self._make_room(directory, need, keep=path)
            fd, tmp = tempfile.mkstemp(prefix=PARTIAL_PREFIX + path.stem + "-", suffix=".npz", dir=directory)
            with os.fdopen(fd, "wb") as f:
                save_recording(f, rec, extra=extra, compress=compress)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, FILE_MODE)
            os.replace(tmp, path)
            cap.path = path
        except OSError as exc:
            self.write_failures += 1
            reason = exc.strerror or str(exc) or type(exc).__name__
            log.warning("recording %s not written: %s (%d so far)", path.name, reason, self.write_failures)
            if tmp is not None:
                try:
                    os.unlink(tmp)
                except OSError:
                    pass
            self.emit("recording_failed", file=path.name, message=reason, failures=self.write_failures)
            return
        if checkpoint:
            log.debug("recording %s: checkpoint written", path.name)
            return
        size = path.stat().st_size
        log.info("recording %s written (%s, %.1f s, %d kB)", path.name, why,
                 rec.imu_t[-1] - rec.imu_t[0], size // 1024)
        self.emit("recording_written", path=str(path), task=cap.task, label=cap.label, reason=why,
                  duration_s=float(rec.imu_t[-1] - rec.imu_t[0]), bytes=size, passes_lost=lost)

    @staticmethod
    def _new_path(directory: pathlib.Path, cap: Capture) -> pathlib.Path:
        path = directory / file_name(cap, datetime.datetime.now())
        n = 2
        while path.exists():
            path = path.with_name(f"{path.stem.rsplit('~', 1)[0]}~{n}.npz")
            n += 1
        return path

    def _make_room(self, directory: pathlib.Path, need: int, keep: pathlib.Path) -> None:
        """Delete the oldest of the daemon's own recordings (never `keep`, never another file) until
        `need` more bytes fit record.max_mb and leave record.keep_free_mb free on the filesystem;
        OSError (ENOSPC) naming the shortfall when they cannot."""
        own = sorted(((f, f.stat()) for f in directory.iterdir() if OWN_NAME.match(f.name) and f != keep),
                     key=lambda fs: fs[1].st_mtime)
        used = sum(st.st_size for _, st in own)
        # with an episode store, only what the store has may go (runtime.uploader.Uploader.may_delete)
        own = [(f, st) for f, st in own if self.may_delete is None or self.may_delete(f)]
        replaced = keep.stat().st_size if keep.exists() else 0
        vfs = os.statvfs(directory)
        free = vfs.f_bavail * vfs.f_frsize + replaced
        keep_free = keep_free_bytes(self.params.keep_free_mb, vfs)
        if free + used - need < keep_free:           # not even with every older recording gone: keep them
            raise OSError(errno.ENOSPC, f"{need / 1e6:.1f} MB would leave {max(free + used - need, 0) / 1e6:.0f} MB "
                                        f"free on the filesystem even without our {len(own)} older recordings, "
                                        f"under record.keep_free_mb ({keep_free / 1e6:.0f} MB)")
        budget = self.params.max_mb * 1e6
        while own and (used + need > budget or free - need < keep_free):
            f, st = own.pop(0)
            try:
                f.unlink()
            except OSError as exc:
                log.warning("recording %s not deleted: %s", f.name, exc.strerror or exc)
                continue
            f.with_name(f.name + UPLOADED_SUFFIX).unlink(missing_ok=True)
            used -= st.st_size
            free += st.st_size
            log.info("recording %s deleted, the oldest: %s", f.name,
                     f"the recordings are over record.max_mb ({self.params.max_mb:g} MB)" if used + need > budget
                     else f"the filesystem keeps record.keep_free_mb ({keep_free / 1e6:.0f} MB) free")
        if free - need < keep_free:                   # an older one could not be deleted
            raise OSError(errno.ENOSPC, f"{need / 1e6:.1f} MB would leave {max(free - need, 0) / 1e6:.0f} MB free "
                                        f"on the filesystem, under record.keep_free_mb ({keep_free / 1e6:.0f} MB)")


def keep_free_bytes(keep_free_mb: float | None, vfs) -> float:
    """record.keep_free_mb in bytes; by default journald's SystemKeepFree=: 15 % of the filesystem, at
    most 4 GiB."""
    if keep_free_mb is not None:
        return keep_free_mb * 1e6
    return min(KEEP_FREE_FRACTION * vfs.f_blocks * vfs.f_frsize, KEEP_FREE_CAP_MB * 1024 * 1024)


def file_name(cap: Capture, now: datetime.datetime) -> str:
    """<time>-<task or 'idle'>[-<label>].npz, with only [A-Za-z0-9_.-] from what a sender gave."""
    parts = [now.strftime("%Y%m%d-%H%M%S"), LABEL_RE.sub("_", cap.task or "idle")[:MAX_LABEL_CHARS]]
    if cap.label:
        parts.append(LABEL_RE.sub("_", cap.label)[:MAX_LABEL_CHARS])
    return "-".join(parts) + ".npz"


def clean_label(label) -> str:
    """A capture's label as the file name will carry it."""
    return LABEL_RE.sub("_", str(label))[:MAX_LABEL_CHARS]


def config_digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]
