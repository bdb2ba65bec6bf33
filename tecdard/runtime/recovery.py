"""`recover` on a thread of its own: the backend's recovery (robots.backend.RobotBackend.recover) takes seconds (UR's
5 s rule before a protective stop may be unlocked, a power-on, franky's error recovery), while the control tick
keeps holding the arm. One at a time, never during a task, and no task starts until it has answered."""
from __future__ import annotations

import logging
import threading
import time

from tecdard.api import commands as C
from tecdard.robots.backend import Recovery
from tecdard.runtime.messages import Reply

log = logging.getLogger("tecdar")

RECOVER_TIMEOUT_S = 20.0        # UR's 5 s rule, a power-on and a brake release, the script uploaded again
SETTLE_S = 2.0                  # a recovery that succeeded: how long its faults may take to clear at the control tick


def recover_hint(code: str, recoverable: frozenset) -> str:
    """What a backend fault's message says about `recover` (every fault names whether it clears it)."""
    return " (`recover` clears it)" if code in recoverable else " (`recover` cannot clear it)"


class Recoverer:
    def __init__(self, robot, outbox, replies, timeout_s: float = RECOVER_TIMEOUT_S, settled=None):
        """`settled()`: True once the control tick holds none of the faults `recover` clears; an `ok` reply waits
        for it (SETTLE_S at most), so that a task sent on it is not refused for a fault the tick has yet to clear."""
        self.robot, self.outbox, self.replies, self.timeout_s = robot, outbox, replies, timeout_s
        self.settled = settled
        self._busy = threading.Event()

    @property
    def busy(self) -> bool:
        return self._busy.is_set()

    def start(self, request: int) -> None:
        """Run the recovery; its reply goes to `request` when it ends."""
        self._busy.set()
        threading.Thread(target=self._run, args=(request,), name="recover", daemon=True).start()

    def _run(self, request: int) -> None:
        t0 = time.monotonic()
        self.outbox.event("recover_started")
        try:
            rec = self.robot.recover(self.timeout_s)
        except Exception as exc:          # a backend's bug: one reply and the log, never the thread's silence
            log.exception("recover")
            rec = Recovery(False, (), f"the recovery failed ({type(exc).__name__}: {exc}); see the log")
        if rec.ok and self.settled is not None:
            settle_by = time.monotonic() + SETTLE_S
            while not self.settled() and time.monotonic() < settle_by:
                time.sleep(0.01)
        took = round(time.monotonic() - t0, 2)
        (log.info if rec.ok else log.warning)("recover: %s%s (%.1f s)", "; ".join(rec.steps) or "nothing done",
                                              "" if rec.ok else f"; a person must: {rec.person}", took)
        self.outbox.event("recovered" if rec.ok else "recover_failed", steps=list(rec.steps), took_s=took,
                          **({} if rec.ok else {"person": rec.person}))
        reply = {"ok": True, "steps": list(rec.steps), "took_s": took} if rec.ok else \
            C.CommandError(C.NOT_RECOVERED, f"recover: {rec.person}").reply()
        self._busy.clear()
        self.replies.put(Reply(request, reply))
