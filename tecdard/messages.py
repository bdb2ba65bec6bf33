"""What the Zenoh (main) thread and the control thread hand each other: frozen records, never Zenoh objects.

A command keeps its Zenoh `Query` in the main thread under a request id; the control thread sees
only the id and answers with a `Reply` carrying it.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StartTask:
    request: int          # the main thread's id of the query to answer
    verb: str             # a task verb of tecdard.commands.TASK_VERBS
    fields: dict          # validated, normalised fields (tecdard.commands.validate)


@dataclass(frozen=True)
class Cancel:
    request: int
    task: str | None      # the task to cancel; None: whichever runs


@dataclass(frozen=True)
class Stop:
    request: int | None   # None: nobody waits for the reply (the daemon's own shutdown)
    reason: str = "stopped by command"


@dataclass(frozen=True)
class Reply:
    request: int
    payload: dict         # the reply object, {"ok": ...}
