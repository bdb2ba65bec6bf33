"""A device's client in a child process of its own, and the daemon's handle on it: the mechanics the UR,
Franka and simulator links share.

Why a child: a client library that blocks with the GIL held (ur-rtde's handshake, `franky.Robot()`
without a timeout) or aborts its process (ur-rtde on a dropped link) costs the child only, and a 1 kHz
loop in it (libfranka's, the simulator's physics) never competes with the daemon's estimator.

The child is `child(settings, cmd_rx, state_tx, *extra_tx)`, started with `spawn`: it reads commands
from `cmd_rx` and sends `(kind, ...)` messages on `state_tx`: first `("ready", ...)` (or `("error",
line)`, any `("note", line)` before), then whatever its link's `_handle` takes, and `("lost", line)`
when its device has gone. A link reads them on a thread of its own (`_read`) and keeps the newest
robot state in a StateSlot for the daemon's threads.
"""
from __future__ import annotations

import multiprocessing
import threading
import time

from tecdard.host import name_os_thread, without_ctrl_c
from tecdard.robots.backend import JointState
from tecdard.robots.backends import BackendError

CHILD_STOP_S = 2.0      # a link's child process is waited for this long, then terminated
# While the daemon rests (no task runs, the arm holds still) a real arm's child sends one state in this
# long instead of every one (a UR's 500 Hz, a Franka's state_rate_hz): each state wakes the link's
# reader, passes the state check and goes through the arm's FK for the estimator, and at rest those
# wake-ups were a good share of the daemon's idle CPU. The newest state is then at most this much older than it would
# be, well inside robot.max_state_age_s (50 ms); a task's start restores the full rate at once.
REST_STATE_PERIOD_S = 0.01


def kill_child(proc) -> None:
    """Terminate a child process that is still alive, and wait for it."""
    if proc is not None and proc.is_alive():
        proc.terminate()
        proc.join(CHILD_STOP_S)


def end_child(proc, conns) -> None:
    """A child process that has been asked to stop: wait for it, terminate it if it does not, and
    close the parent's ends of its pipes (a link that reconnects makes new ones)."""
    proc.join(CHILD_STOP_S)
    kill_child(proc)
    for conn in conns:
        conn.close()


class StateSlot:
    """The newest JointState of a robot link, between the thread that receives states and the
    threads that read them: `publish` replaces it and wakes the waiters; `close` (the link has gone)
    wakes them for good, and reads then raise `error()`."""

    def __init__(self, error):
        self._error = error                  # () -> the exception to raise once closed or before a state
        self._state: JointState | None = None
        self._cond = threading.Condition()
        self.closed = threading.Event()

    def publish(self, js: JointState) -> None:
        with self._cond:
            self._state = js
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed.set()
            self._cond.notify_all()

    def read(self) -> JointState:
        if self._state is None:
            raise self._error()
        return self._state

    def wait(self, seq: int, timeout: float) -> JointState:
        """The newest state once its seq differs from `seq`, or after `timeout` s."""
        with self._cond:
            self._cond.wait_for(lambda: self.closed.is_set() or (self._state is not None and self._state.seq != seq),
                                timeout)
        if self.closed.is_set():
            raise self._error()
        return self.read()


class ChildLink:
    """The daemon's handle on a child: its command pipe, its message reader, the newest state and the
    child's end. A subclass names its child (`child`, `process_name`), its error class and the
    lines it says at start (`_no_answer`, `_ended`, `_refused`), takes its messages (`_handle`) and
    turns what the child read into JointStates, which `_publish` hands on once they pass the
    backend's `gate` (robots.state_check)."""

    error = BackendError
    process_name = "tecdar-link"
    extra_pipes = 0                  # child -> daemon pipes beside the state pipe (the simulator's IMU)
    reader_name = "link"

    def __init__(self, settings, start_timeout_s: float):
        self.settings = settings
        self.start_timeout_s = start_timeout_s
        self._proc = None
        self._cmd = self._state_rx = None
        self._extra_rx: list = []
        self._send_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._states = StateSlot(lambda: self.error(self.fault or self._refused_states() or self._no_state()))
        self.exited = self._states.closed
        self.fault: str | None = None               # the link's own fault (lost), or None
        self.gate = None                            # robots.state_check.StateCheck: what a state must pass
        self.on_state = None                        # called with every state that passes, on the reader
        self.notes: list[str] = []                  # what the child said before it was ready

    @staticmethod
    def child(settings, cmd_rx, state_tx, *extra_tx) -> None:
        raise NotImplementedError

    # -- what a subclass says ----------------------------------------------------------------
    def _no_answer(self, timeout_s: float) -> str:
        return f"no answer within {timeout_s:g} s"

    def _ended(self, exitcode) -> str:
        return f"the link ended at start (exit code {exitcode})"

    def _refused(self, reason: str) -> str:
        return f"the link was refused: {reason}"

    def _no_state(self) -> str:
        return "no state yet"

    def _not_running(self) -> str:
        return "the link is not running"

    def _refused_states(self) -> str | None:
        """Why the states that came were refused (the gate's fault), or None."""
        return None if self.gate is None else self.gate.fault

    def _handle(self, msg: tuple) -> None:
        """One message from the child after `ready` (its kind first)."""

    def _ready(self, payload: tuple) -> None:
        """What the child sent with `ready`."""

    def _gone(self) -> None:
        """The child's state pipe has closed (after `lost`, or with the child)."""

    # -- lifecycle ---------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """The child was started and has not been stopped (it may still have lost its device)."""
        return self._proc is not None

    def start(self) -> None:
        """Start the child and wait for its `ready` within start_timeout_s, or raise `error` with the
        subclass's line; then read its messages on a thread of its own."""
        self._spawn()
        self._ready(self._await_ready())
        self._reader = threading.Thread(target=self._read, name=self.reader_name, daemon=True)
        self._reader.start()

    def _spawn(self) -> None:
        ctx = multiprocessing.get_context("spawn")     # never fork a process that already runs Zenoh's threads
        cmd_rx, self._cmd = ctx.Pipe(duplex=False)
        self._state_rx, state_tx = ctx.Pipe(duplex=False)
        extra = [ctx.Pipe(duplex=False) for _ in range(self.extra_pipes)]
        self._extra_rx = [rx for rx, _ in extra]
        self._proc = ctx.Process(target=without_ctrl_c, name=self.process_name, daemon=True,
                                 args=(type(self).child, self.settings, cmd_rx, state_tx, *(tx for _, tx in extra)))
        self._proc.start()
        for end in (cmd_rx, state_tx, *(tx for _, tx in extra)):
            end.close()      # the child holds its own copies: EOF on either side means the other has gone

    def _await_ready(self) -> tuple:
        deadline = time.monotonic() + self.start_timeout_s
        try:
            while True:
                left = deadline - time.monotonic()
                if left <= 0 or not self._state_rx.poll(left):
                    raise self.error(self._no_answer(self.start_timeout_s))
                msg = self._state_rx.recv()
                if msg[0] != "note":
                    break
                self.notes.append(msg[1])
        except EOFError:
            kill_child(self._proc)
            raise self.error(self._ended(self._proc.exitcode)) from None
        except BackendError:
            kill_child(self._proc)
            raise
        if msg[0] != "ready":
            kill_child(self._proc)
            raise self.error(self._refused(msg[1]))
        return msg[1:]

    def _read(self) -> None:
        name_os_thread(self.reader_name)       # top -H and `status` tell the link's reader apart
        while True:
            try:
                msg = self._state_rx.recv()
            except (EOFError, OSError):
                break
            if msg[0] == "lost":
                self.fault = msg[1]
                break                        # the child may hang in its client's reconnect: stop() ends it
            self._handle(msg)
        self._gone()
        self._states.close()

    def stop(self) -> None:
        """Tell the child to close, wait for it (terminate it if it does not end), close the pipes."""
        if self._proc is None:
            return
        self._send(("close",), quiet=True)
        end_child(self._proc, (self._cmd, self._state_rx, *self._extra_rx))
        self._proc = None

    def set_resting(self, resting: bool) -> None:
        """The daemon rests (True: the child may send one state per REST_STATE_PERIOD_S) or a task
        has started (False: every state). A child that does not pace its states ignores it."""
        self._send(("rest", REST_STATE_PERIOD_S if resting else 0.0), quiet=True)

    def _send(self, msg: tuple, quiet: bool = False) -> None:
        try:
            with self._send_lock:
                self._cmd.send(msg)
        except (OSError, ValueError, AttributeError, BrokenPipeError):
            if not quiet:
                raise self.error(self._not_running()) from None

    # -- receive -------------------------------------------------------------------------------
    def _publish(self, js: JointState) -> None:
        """A state the child read, for the daemon's threads (and `on_state`) once it passes the gate;
        a state that fails is dropped (the gate holds the fault naming it)."""
        if self.gate is None or self.gate.admit(js):
            self._states.publish(js)
            if self.on_state is not None:
                self.on_state(js)             # the backend's feed_states (the estimator's proprioception)

    def read_state(self) -> JointState:
        return self._states.read()

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s; the link's error
        once it has gone."""
        return self._states.wait(seq, timeout)
