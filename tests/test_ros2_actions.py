"""Issue 51 item 3: the task verbs as ROS 2 actions, driven as rcl_action's client drives a server over rmw_zenoh:
the keys come from the node's liveliness tokens, every request and reply carries rmw_zenoh's attachment, the stock
types (action_msgs' CancelGoal and GoalStatusArray, the UUID) are rclpy's own serialisation, and tecdar_msgs' action
types are our TypeSupport's, whose hashes rosidl's generator confirms (tests/test_ros2_wire.py). A Zenoh router
between the daemon and the client, as `rmw_zenohd` would be."""
import json
import math
import os
import threading
import time

import numpy as np
import pytest
import zenoh

from tecdard.api.session import session_config
from tecdard.ros2 import rmw
from tecdard.ros2.typesupport import TypeSupport
from tecdard.tools.demo import distance_to_axis
from tests.test_ros2_node import HINGE_TOL_M, ros2_daemon, router  # noqa: F401  (the router fixture)

pytest.importorskip("rclpy", reason="rclpy's wheels are installed by `make test` (extra ros2-test)")
pytestmark = pytest.mark.slow

UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
RESULT_WAIT_S = 90.0
NAN = float("nan")


class ActionClient:
    """One action of the node (`/sim/<verb>`), as rcl_action's client reaches it over rmw_zenoh."""

    def __init__(self, session: zenoh.Session, verb: str, ts: TypeSupport):
        self.s, self.verb, self.ts = session, verb, ts
        self.action = ts.actions[f"tecdar_msgs/action/{verb.capitalize()}"]
        prefix = f"/sim/{verb}/_action/"
        tokens = [rmw.parse_token(str(r.ok.key_expr)) for r in session.liveliness().get("@ros2_lv/**", timeout=2.0)
                  if r.ok is not None]
        self.keys = {t.name[len(prefix):]: rmw.data_keyexpr(0, t.name, t.dds_type, t.type_hash)
                     for t in tokens if t.name.startswith(prefix)}
        assert set(self.keys) == {"send_goal", "cancel_goal", "get_result", "feedback", "status"}, self.keys
        self.seq = 0
        self.feedback: list = []
        self.statuses: list = []
        self._subs = [session.declare_subscriber(self.keys["feedback"], self._on_feedback),
                      session.declare_subscriber(self.keys["status"], self._on_status)]

    def _on_feedback(self, sample) -> None:
        self.feedback.append(self.ts.decode(sample.payload.to_bytes(), self.action.feedback_message))

    def _on_status(self, sample) -> None:
        from action_msgs.msg import GoalStatusArray
        from rclpy import serialization
        msg = serialization.deserialize_message(sample.payload.to_bytes(), GoalStatusArray)
        self.statuses.append({bytes(s.goal_info.goal_id.uuid): s.status for s in msg.status_list})

    def _call(self, name: str, payload: bytes, timeout: float = 10.0) -> bytes:
        self.seq += 1
        replies = list(self.s.get(self.keys[name], payload=payload, timeout=timeout,
                                  attachment=rmw.attachment(self.seq, time.time_ns(), bytes(range(16)))))
        assert len(replies) == 1 and replies[0].ok is not None, (name, replies)
        assert rmw.parse_attachment(replies[0].ok.attachment.to_bytes())[0] == self.seq
        return replies[0].ok.payload.to_bytes()

    def uuid(self, raw: bytes):
        return self.ts.cls("unique_identifier_msgs/msg/UUID")(uuid=np.frombuffer(raw, dtype=np.uint8).copy())

    def send_goal(self, uuid: bytes, **goal):
        fields = {"angle_deg": NAN, "speed": NAN, "probe_distance": NAN, "direction": np.zeros(0), "strategy": "",
                  "turn_tool": 0} if self.verb == "rotate" else {}
        goal_msg = self.ts.cls(self.action.goal)(**{**fields, **goal})
        req = self.ts.cls(self.action.send_goal.request)(goal_id=self.uuid(uuid), goal=goal_msg)
        raw = self._call("send_goal", self.ts.encode(req, self.action.send_goal.request))
        return self.ts.decode(raw, self.action.send_goal.response)

    def get_result(self, uuid: bytes, timeout: float = RESULT_WAIT_S):
        req = self.ts.cls(self.action.get_result.request)(goal_id=self.uuid(uuid))
        raw = self._call("get_result", self.ts.encode(req, self.action.get_result.request), timeout)
        return self.ts.decode(raw, self.action.get_result.response)

    def cancel(self, uuid: bytes = bytes(16), stamp_s: float = 0.0):
        from action_msgs.msg import GoalInfo
        from action_msgs.srv import CancelGoal
        from builtin_interfaces.msg import Time
        from rclpy import serialization
        from unique_identifier_msgs.msg import UUID
        req = CancelGoal.Request(goal_info=GoalInfo(goal_id=UUID(uuid=list(uuid)),
                                                    stamp=Time(sec=int(stamp_s), nanosec=0)))
        raw = self._call("cancel_goal", serialization.serialize_message(req))
        return serialization.deserialize_message(raw, CancelGoal.Response)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def wait_until(predicate, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_rotate_is_an_action_with_feedback_a_held_result_and_a_cancel(tmp_path, router):  # noqa: F811
    """A refused goal, then a rotate to its end (feedback with the phase, progress, travel and the live contact
    with its sigmas; get_result held open for the whole task; the hinge within the rotate tests' tolerance), a
    second rotate cancelled mid-way through cancel_goal, and the status array through it all."""
    d = ros2_daemon(tmp_path, router)
    ts = TypeSupport()
    try:
        with zenoh.open(session_config([], [f"tcp/127.0.0.1:{router}"], mode="client")) as s:
            rotate = ActionClient(s, "rotate", ts)
            # refused by the same validation as the Zenoh verb: not accepted, its code is its result
            bad = os.urandom(16)
            assert rotate.send_goal(bad, angle_deg=500.0).accepted is False
            refused = rotate.get_result(bad, timeout=5.0)
            assert refused.status == ABORTED and refused.result.error_code == "out_of_limits", refused
            assert rotate.get_result(os.urandom(16), timeout=5.0).status == UNKNOWN

            # a rotate to its end; its result asked for at once, answered when the task ends
            goal = os.urandom(16)
            sent = rotate.send_goal(goal, angle_deg=20.0)
            assert sent.accepted is True and sent.stamp.sec > 0, sent
            assert rotate.send_goal(goal, angle_deg=20.0).accepted is False        # a goal id is used once
            assert wait_until(lambda: any(st.get(goal) == EXECUTING for st in rotate.statuses), 5.0), rotate.statuses
            held: dict = {}
            asker = threading.Thread(target=lambda: held.update(r=rotate.get_result(goal), t=time.monotonic()))
            t_asked = time.monotonic()
            asker.start()
            asker.join(RESULT_WAIT_S + 5.0)
            res = held["r"]
            assert res.status == SUCCEEDED and res.result.ok is True, res
            assert held["t"] - t_asked > 1.0                         # the query stayed open while the arm turned
            result = json.loads(res.result.result_json)
            sim = result["sim"]
            err = distance_to_axis(np.array(result["hinge"]["p"]), np.array(sim["hinge_point"]),
                                   np.array(sim["hinge_axis"]))
            assert err < HINGE_TOL_M, err
            print(f"result held {held['t'] - t_asked:.2f} s, hinge error {err * 1e3:.2f} mm, "
                  f"{len(rotate.feedback)} feedback messages")
            fb = [m.feedback for m in rotate.feedback if bytes(m.goal_id.uuid) == goal]
            assert len(fb) >= 5 and all(f.task == res.result.task for f in fb)
            assert {f.phase for f in fb} >= {"probe", "arc"}, {f.phase for f in fb}
            progress = [f.progress for f in fb]
            assert progress == sorted(progress) and 0.0 <= progress[0] and progress[-1] <= 1.0
            assert max(f.travel_m for f in fb) > 0.02                 # 20 deg on a 150 mm handle is 52 mm of arc
            live = [f for f in fb if f.contact_valid]
            assert live and all(np.all(np.isfinite(f.contact_std_m)) and np.all(f.contact_std_m > 0) for f in live)
            last = live[-1]
            p = np.array([last.contact_point.x, last.contact_point.y, last.contact_point.z])
            assert distance_to_axis(p, np.array(sim["hinge_point"]), np.array(sim["hinge_axis"])) < HINGE_TOL_M
            assert math.isfinite(last.angle_deg)
            assert all(not f.contact_valid and math.isnan(f.angle_deg) for f in fb if f not in live)
            assert wait_until(lambda: rotate.statuses and rotate.statuses[-1].get(goal) == SUCCEEDED, 5.0)
            assert rotate.get_result(goal, timeout=5.0).status == SUCCEEDED        # kept after its end

            # a second rotate, cancelled once it turns
            second = os.urandom(16)
            assert rotate.send_goal(second, angle_deg=20.0).accepted is True
            assert wait_until(lambda: any(bytes(m.goal_id.uuid) == second and m.feedback.progress > 0.0
                                          for m in rotate.feedback), 30.0)
            assert rotate.cancel(os.urandom(16)).return_code == 2                  # ERROR_UNKNOWN_GOAL_ID
            assert rotate.cancel(goal).return_code == 3                            # ERROR_GOAL_TERMINATED
            reply = rotate.cancel(second)
            assert reply.return_code == 0 and [bytes(g.goal_id.uuid) for g in reply.goals_canceling] == [second]
            ended = rotate.get_result(second, timeout=30.0)
            assert ended.status == CANCELED and ended.result.error_code == "cancelled", ended
            assert wait_until(lambda: rotate.statuses[-1].get(second) == CANCELED, 5.0)
            assert CANCELING in [st.get(second) for st in rotate.statuses]
            assert d.client.command("status")["state"]["task"] is None
            rotate.close()
    finally:
        d.close()
    assert "Traceback" not in d.log()
