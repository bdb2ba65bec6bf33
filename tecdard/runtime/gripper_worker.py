"""The gripper's own thread: the grasps and releases the control thread hands over (each blocks until the fingers
stop: up to gripper.timeout_s), and between them the gripper's state, polled, for `state` and the estimator.

Nothing else ever waits on the gripper: the control thread reads `latest` and hands jobs over without blocking,
and a stop reaches the gripper on a thread of its own (a Robotiq's socket may be busy with a poll)."""
from __future__ import annotations

import logging
import queue
import threading

from tecdard.api import commands as C
from tecdard.robots.gripper import Gripper, GripperError, GripperParams, GripState
from tecdard.runtime.messages import Grip, LatestValue, Reply

log = logging.getLogger("tecdar.gripper")

POLL_S = 0.1                   # the state between jobs: 10 Hz


class GripperWorker:
    def __init__(self, gripper: Gripper, params: GripperParams, outbox, replies):
        self.gripper, self.params, self.outbox, self.replies = gripper, params, outbox, replies
        self.latest: LatestValue = LatestValue()
        self.latest.set(gripper.state())
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._busy = threading.Event()

    @property
    def kind(self) -> str:
        return self.gripper.kind

    @property
    def busy(self) -> bool:
        """A grasp or a release was accepted and has not finished."""
        return self._busy.is_set()

    def state(self) -> GripState:
        return self.latest.get()

    def holds_nothing(self) -> bool:
        """The gripper says it holds nothing (a gripper that cannot say never does)."""
        st = self.latest.get()
        return self.gripper.reports_grasp and st is not None and st.grasped is False

    def submit(self, msg: Grip) -> bool:
        """Hand a grasp or release over; False when one runs already."""
        if self._busy.is_set():
            return False
        self._busy.set()
        self._jobs.put_nowait(msg)
        return True

    def stop(self) -> None:
        """The fingers stop where they are (the daemon's `stop`), without waiting for the gripper."""
        threading.Thread(target=self.gripper.stop, name="gripper-stop", daemon=True).start()

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                msg = self._jobs.get(timeout=POLL_S)
            except queue.Empty:
                self._poll()
                continue
            try:
                self._do(msg)
            finally:
                self._busy.clear()
        self.gripper.close()

    def _poll(self) -> None:
        try:
            self.latest.set(self.gripper.state())
        except Exception:                  # a gripper's bug must not end its thread
            log.exception("gripper state")

    def _do(self, msg: Grip) -> None:
        p = self.params
        f = {k: v for k, v in msg.fields.items() if v is not None}       # a field not given: the config's
        speed = f.get("speed_m_s", p.speed_m_s)
        try:
            if msg.verb == "grasp":
                st = self.gripper.grasp(f.get("force_n", p.force_n), f.get("width_m", p.width_m), speed, p.timeout_s)
            else:
                st = self.gripper.release(f.get("width_m", p.open_width_m), speed, p.timeout_s)
        except GripperError as exc:
            self._poll()
            log.warning("%s: %s", msg.verb, exc)
            self.outbox.event("gripper", action=msg.verb, ok=False, error=str(exc),
                              gripper=self.state().to_json(self.kind))
            self.replies.put(Reply(msg.request, C.CommandError(C.GRIPPER, f"{msg.verb}: {exc}").reply()))
            return
        except Exception as exc:           # a bug of ours: one reply and the log, never the thread
            log.exception("%s", msg.verb)
            self.replies.put(Reply(msg.request, C.CommandError(C.INTERNAL, f"{msg.verb}: {exc}").reply()))
            return
        self.latest.set(st)
        body = st.to_json(self.kind)
        log.info("%s: %s", msg.verb, body)
        self.outbox.event("gripper", action=msg.verb, ok=True, gripper=body)
        if msg.verb == "grasp" and self.gripper.reports_grasp and not st.grasped:
            self.replies.put(Reply(msg.request, C.CommandError(
                C.NOT_GRASPED, f"grasp: the fingers closed on nothing (opening {_mm(st.width_m)})").reply()))
            return
        self.replies.put(Reply(msg.request, {"ok": True, "gripper": body}))


def _mm(x: float | None) -> str:
    return "unknown" if x is None else f"{x * 1e3:.1f} mm"
