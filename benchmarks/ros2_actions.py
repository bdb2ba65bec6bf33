"""The task verbs as ROS 2 actions (issue 51): the round trip's latency, what the action server adds to the publish
pass, and the control tick with the node on; writes benchmarks/ros2_actions.md.

    python -m benchmarks.ros2_actions [--goals N]

- Round trip: a client of our own that does on the wire what rcl_action's does (tests/test_ros2_actions.py:
  ActionClient), through a Zenoh router on loopback, sends N `rotate` goals of 10 degrees one after the other,
  subscribed to the action's feedback and status. For each: send_goal's reply after the request (accepted), the
  first feedback after that reply, and get_result's reply (asked at once, held open) after the task's `task_done`
  event was stamped in the daemon (the same monotonic clock: one host).
- The publish pass: building and encoding one FeedbackMessage and one GoalStatusArray (rosbags), microseconds.
- The tick: the control thread's lateness p99, work p99 and overruns over its last 1000 ticks, from `status`
  after the goals (the node on, the feedback subscribed).
The machine is shared: the figures vary from run to run; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import platform
import sys
import tempfile
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from tecdard.api.session import session_config  # noqa: E402
from tecdard.ros2.typesupport import TypeSupport  # noqa: E402
from tecdard.runtime.ros2_actions import ActionServer, Goal, _Action  # noqa: E402
from tests.test_ros2_actions import ActionClient  # noqa: E402
from tests.test_ros2_node import ros2_daemon, start_router  # noqa: E402

ENCODE_N = 2000
ANGLE_DEG = 10.0


def encode_costs() -> dict[str, float]:
    """µs to build and encode one feedback message and one status array, on a server without a session."""
    class Node:
        ts = TypeSupport()
        counters = {"published": 0}
    node = Node()
    server = ActionServer(node)
    act = _Action("rotate", node.ts.actions["tecdar_msgs/action/Rotate"])
    sent: list = []

    class Pub:
        def put(self, payload, attachment=None):
            sent.append(len(payload))

        class matching_status:
            matching = True
    act.feedback, act.status = (Pub(), bytes(16), [0]), (Pub(), bytes(16), [0])
    server.actions.append(act)
    goal = Goal(os.urandom(16), "rotate", time.time(), time.monotonic(), task="rotate-1")
    server.goals[goal.uuid], server.by_task[goal.task] = goal, goal
    state = {"task": {"id": "rotate-1", "phase": "arc", "progress": 0.5}, "tcp": {"p": [0.3, 0.0, 0.4]},
             "contact": {"p": [0.2, 0.0, 0.4], "std": [1e-3] * 3, "axis": [0.0, 1.0, 0.0], "angle_deg": 12.0,
                         "onset_t": time.monotonic()}}
    out = {}
    for name, fn in (("feedback", lambda: (setattr(goal, "feedback_t", -1e9), server._feedback(state))),
                     ("status", lambda: server._publish_status(act))):
        times = []
        for _ in range(ENCODE_N):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[name] = float(np.median(times)) * 1e6
    return out


def round_trips(goals: int) -> tuple[list[dict], dict]:
    with tempfile.TemporaryDirectory() as tmp:
        port, router = start_router()
        try:
            d = ros2_daemon(pathlib.Path(tmp), port)
            try:
                rows = []
                with zenoh.open(session_config([], [f"tcp/127.0.0.1:{port}"], mode="client")) as s:
                    client = ActionClient(s, "rotate", TypeSupport())
                    time.sleep(1.0)
                    for _ in range(goals):
                        uuid = os.urandom(16)
                        t0 = time.monotonic()
                        sent = client.send_goal(uuid, angle_deg=ANGLE_DEG)
                        t_accepted = time.monotonic()
                        if not sent.accepted:
                            rows.append({"accepted": False})
                            continue
                        held: dict = {}
                        asker = threading.Thread(target=lambda: held.update(r=client.get_result(uuid),
                                                                            t=time.monotonic()))
                        asker.start()
                        first = None
                        while first is None and time.monotonic() - t_accepted < 30.0:
                            first = next((m for m in client.feedback if bytes(m.goal_id.uuid) == uuid), None)
                            time.sleep(0.001)
                        t_first = time.monotonic()
                        asker.join(120.0)
                        task = held["r"].result.task
                        ev = next(e for e in d.client.event_log if e.get("task") == task
                                  and e["kind"] in ("task_done", "task_failed"))
                        rows.append({"accepted": True, "accept_ms": (t_accepted - t0) * 1e3,
                                     "first_feedback_ms": (t_first - t_accepted) * 1e3,
                                     "result_ms": (held["t"] - ev["t"]) * 1e3, "status": int(held["r"].status),
                                     "error": held["r"].result.error_message})
                        time.sleep(0.5)
                    client.close()
                ctl = d.client.command("status")["state"]["control"]
                return rows, ctl
            finally:
                d.close()
        finally:
            router.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    # two: the third 10 deg rotate in a row stops on divergence, the fingertips' twist having added up to their
    # stick limit (docs/estimation.md, "Rotates in a row")
    ap.add_argument("--goals", type=int, default=2, help="rotate goals of 10 deg, one after the other")
    args = ap.parse_args()
    costs = encode_costs()
    rows, ctl = round_trips(args.goals)
    ok = [r for r in rows if r["accepted"]]

    def cell(key: str) -> str:
        v = [r[key] for r in ok]
        return f"{np.median(v):.1f} ({min(v):.1f}-{max(v):.1f})" if v else "-"
    text = f"""# The task verbs as ROS 2 actions ({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, \
Python {platform.python_version()})

`python -m benchmarks.ros2_actions`. The machine is shared; nothing here is a test.

## Round trip ({len(ok)} of {len(rows)} `rotate` goals of {ANGLE_DEG:g} deg accepted, through a router on loopback)

A client of our own doing on the wire what rcl_action's does (tests/test_ros2_actions.py), subscribed to the
feedback and the status. Median (min-max), ms.

| goal accepted (send_goal's reply) | first feedback after it | result after `task_done` (get_result held open) |
|---|---|---|
| {cell("accept_ms")} | {cell("first_feedback_ms")} | {cell("result_ms")} |

Statuses: {", ".join(str(r.get("status")) for r in rows)} (4: SUCCEEDED, 6: ABORTED). {"; ".join(r["error"] for r in ok if r.get("error"))}

## The publish pass

| message | µs to build and encode (median of {ENCODE_N}) |
|---|---|
| feedback (`Rotate_FeedbackMessage`) | {costs["feedback"]:.1f} |
| status (`GoalStatusArray`, one goal) | {costs["status"]:.1f} |

At 10 Hz of feedback while a goal runs, about {costs["feedback"] * 10 / 1e4:.3f} % of one core; the status is sent on a \
goal's changes only.

## The control tick with the node on and the feedback subscribed (its last 1000 ticks, after the goals)

| lateness p99 | work p99 | overruns |
|---|---|---|
| {ctl.get("late_ms_p99")} ms | {ctl.get("work_ms_p99")} ms | {ctl.get("overruns")} |
"""
    (ROOT / "benchmarks" / "ros2_actions.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
