"""The task verbs as ROS 2 actions over rmw_zenoh: what rcl_action puts on the wire for an action server, served
by the node on the main thread beside its services (tecdar_msgs/action/<Verb>; docs/ros2.md, "Actions").

Under `<namespace>/<verb>/_action/` an action is three services and two topics, as rcl_action names them:
- `send_goal` (Verb_SendGoal): the goal goes through the daemon's command intake as the Zenoh verb of the same
  name, with the same budget, validation, limits and refusals; accepted is the intake's `ok`. A refused goal's
  code and message are its result (get_result: STATUS_ABORTED), since SendGoal's response has no room for them;
- `cancel_goal` (action_msgs/CancelGoal): rcl_action's selection (one goal, every goal, or those accepted at or
  before a stamp), each cancelled through the intake's `cancel`;
- `get_result` (Verb_GetResult): answered at once for a goal that has ended, else held (the Zenoh query stays
  open) and answered when the task ends, as rmw_zenoh's service clients wait without a timeout;
- `feedback` (Verb_FeedbackMessage): the task's phase, progress, travel and the live contact, at most
  FEEDBACK_PERIOD_S apart, while someone subscribes;
- `status` (action_msgs/GoalStatusArray): every goal kept, on each change; transient local with a depth of 1
  (a Zenoh advanced publisher with a one-sample cache, as rmw_zenoh makes a transient-local publisher).
"""
from __future__ import annotations

import collections
import json
import logging
import math
import time
from dataclasses import dataclass, field

import zenoh
import zenoh.ext

from tecdard import verbs as task_verbs
from tecdard.ros2 import messages as M
from tecdard.ros2 import rmw
from tecdard.ros2.typesupport import CANCEL_GOAL, CANCEL_GOAL_SRV, ActionType, TypeError_
from tecdard.runtime.ros2_parameters import _bytes

log = logging.getLogger("tecdar.ros2")

SERVICE_QOS = rmw.RELIABLE_10                                        # rmw_qos_profile_services_default
FEEDBACK_QOS = rmw.RELIABLE_10                                       # rmw_qos_profile_default
STATUS_QOS = rmw.Qos(rmw.RELIABLE, rmw.TRANSIENT_LOCAL, rmw.KEEP_LAST, 1)   # rcl_action_qos_profile_status_default
GOAL_STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"
BACKLOG = 16                     # requests waiting per service (the oldest overwritten)
FEEDBACK_PERIOD_S = 0.1          # feedback at 10 Hz at most (the state comes at the tick's 50 Hz)
RESULT_TIMEOUT_S = 900.0         # an ended goal's result is kept this long (rcl_action's default result_timeout)
MAX_GOALS = 64                   # and no more than this many goals, the oldest ended ones forgotten first
MAX_REFUSED = 64                 # refused goals whose refusal get_result can still read
MAX_WAITING = 64                 # get_result queries held open per running goal
ONSET_SLACK_S = 0.1              # a contact whose onset is this much before the goal's acceptance is still its own

# action_msgs/msg/GoalStatus
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
ENDED = (SUCCEEDED, CANCELED, ABORTED)
# action_msgs/srv/CancelGoal's return codes
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = range(4)


@dataclass
class Goal:
    uuid: bytes
    verb: str
    stamp_s: float                         # accepted, system clock
    t_accepted: float                      # accepted, monotonic (the daemon's clock)
    task: str = ""
    status: int = EXECUTING
    result: dict | None = None             # the Result's fields once it ended
    ended_t: float = math.inf
    waiting: list = field(default_factory=list)   # held get_result queries: (query, seq, client gid)
    start_p: list | None = None            # the TCP where the task's first state found it
    feedback_t: float = -math.inf


@dataclass
class _Action:
    verb: str
    types: ActionType
    rings: dict = field(default_factory=dict)       # send_goal, cancel_goal, get_result -> queryable ring
    feedback: tuple | None = None                   # (zenoh publisher, gid, [seq])
    status: tuple | None = None                     # (zenoh advanced publisher, gid, [seq])


class _Call:
    """A goal or a cancel as the intake sees a Zenoh query: its key, its JSON payload, and `reply`, which hands the
    intake's answer to `on_reply` (on the main thread: the intake answers there)."""

    def __init__(self, key_expr: str, payload: bytes, on_reply):
        self.key_expr, self.payload, self._on_reply = key_expr, payload, on_reply

    def reply(self, _key, text: str, encoding=None) -> None:
        self._on_reply(json.loads(text))


class ActionServer:
    """Every task verb with an action type in tecdar_msgs, for `node` (runtime.ros2_node.Ros2Node: its type support,
    entities, intake and counters). Owned by the main thread: requests in `poll`, the daemon's messages in
    `on_telemetry`."""

    def __init__(self, node):
        self.node = node
        self.actions: list[_Action] = []
        self.goals: collections.OrderedDict[bytes, Goal] = collections.OrderedDict()
        self.by_task: dict[str, Goal] = {}
        self.refused: collections.OrderedDict[bytes, dict] = collections.OrderedDict()
        self._ended: collections.OrderedDict[str, dict] = collections.OrderedDict()   # task id -> its end event

    # -- declaring ------------------------------------------------------------------------------
    def declare(self, session: zenoh.Session) -> None:
        node = self.node
        node.ts.add_service(CANCEL_GOAL_SRV, CANCEL_GOAL)
        for verb in task_verbs.names():
            types = node.ts.actions.get(f"tecdar_msgs/action/{verb.capitalize()}")
            if types is None:
                log.warning("ROS 2: no tecdar_msgs/action/%s: the verb %s is no action", verb.capitalize(), verb)
                continue
            act = _Action(verb, types)
            for name, srv_type in (("send_goal", types.send_goal.name), ("cancel_goal", CANCEL_GOAL),
                                   ("get_result", types.get_result.name)):
                key, _ = node._entity(rmw.SERVICE, f"{verb}/_action/{name}", srv_type, SERVICE_QOS)
                act.rings[name] = session.declare_queryable(key, zenoh.handlers.RingChannel(BACKLOG), complete=True)
                node._declared.append(act.rings[name])
            key, token = node._entity(rmw.PUBLISHER, f"{verb}/_action/feedback", types.feedback_message, FEEDBACK_QOS)
            act.feedback = (session.declare_publisher(key), rmw.gid(token), [0])
            key, token = node._entity(rmw.PUBLISHER, f"{verb}/_action/status", GOAL_STATUS_ARRAY, STATUS_QOS)
            status = zenoh.ext.declare_advanced_publisher(session, key, cache=zenoh.ext.CacheConfig(1),
                                                          publisher_detection=True)
            act.status = (status, rmw.gid(token), [0])
            node._declared += [act.feedback[0], status]
            self.actions.append(act)
            self._publish_status(act)

    def _action(self, verb: str) -> _Action:
        return next(a for a in self.actions if a.verb == verb)

    # -- requests (the main thread) ----------------------------------------------------------------------
    def poll(self, now: float) -> int:
        n = 0
        for act in self.actions:
            for name, ring in act.rings.items():
                for _ in range(BACKLOG):
                    query = ring.try_recv()
                    if query is None:
                        break
                    n += 1
                    self.node.counters["requests"] += 1
                    self._request(act, name, query, now)
        self._expire(now)
        return n

    def _request(self, act: _Action, name: str, query, now: float) -> None:
        node = self.node
        try:
            seq, _t, client_gid = rmw.parse_attachment(_bytes(query.attachment))
        except ValueError as exc:
            node.counters["bad_requests"] += 1
            log.info("ROS 2 %s/_action/%s: request refused: %s", act.verb, name, exc)
            return
        srv_type = {"send_goal": act.types.send_goal.name, "cancel_goal": CANCEL_GOAL,
                    "get_result": act.types.get_result.name}[name]

        def answer(msg) -> None:
            try:
                query.reply(query.key_expr, node.ts.encode(msg, srv_type + "_Response"),
                            attachment=rmw.attachment(seq, time.time_ns(), client_gid))
            except Exception:
                log.exception("ROS 2 %s/_action/%s: the reply was not sent", act.verb, name)
        size = len(query.payload) if query.payload is not None else 0
        verb = {"send_goal": act.verb, "cancel_goal": "cancel", "get_result": "status"}[name]
        refusal = _Call("", b"", lambda reply: self._over_budget(act, name, answer, reply))
        if not node.intake.charge(refusal, node.intake.keys.cmd(verb), size, now):
            return
        try:
            req = node.ts.decode(_bytes(query.payload) or b"", srv_type + "_Request")
        except (TypeError_, ValueError) as exc:
            node.counters["bad_requests"] += 1
            log.info("ROS 2 %s/_action/%s: request refused: %s", act.verb, name, str(exc)[:200])
            self._over_budget(act, name, answer, {"ok": False, "error": {"code": "bad_request", "message": str(exc)}})
            return
        if name == "send_goal":
            self._send_goal(act, req, answer, now)
        elif name == "cancel_goal":
            self._cancel(act, req, answer, now)
        else:
            self._get_result(act, bytes(req.goal_id.uuid), query, seq, client_gid, answer)

    def _over_budget(self, act: _Action, name: str, answer, reply: dict) -> None:
        """A request refused before it was read (over its class's budget, too large, undecodable): a goal is not
        accepted, a cancel rejected, a result unknown."""
        ts = self.node.ts
        if name == "send_goal":
            answer(ts.cls(act.types.send_goal.response)(accepted=False, stamp=M.ros_time(ts, time.time())))
        elif name == "cancel_goal":
            answer(ts.cls(CANCEL_GOAL + "_Response")(return_code=ERROR_REJECTED, goals_canceling=[]))
        else:
            answer(self._result_response(act, UNKNOWN, _result(reply)))

    def _send_goal(self, act: _Action, req, answer, now: float) -> None:
        ts, uuid = self.node.ts, bytes(req.goal_id.uuid)
        response = ts.cls(act.types.send_goal.response)
        if uuid in self.goals or uuid in self.refused:
            answer(response(accepted=False, stamp=M.ros_time(ts, time.time())))
            return
        try:
            payload = json.dumps(M.request_payload(task_verbs.get(act.verb).fields, req.goal)).encode()
        except ValueError as exc:
            self._refuse(uuid, {"ok": False, "error": {"code": "bad_request", "message": str(exc)}})
            answer(response(accepted=False, stamp=M.ros_time(ts, time.time())))
            return

        def on_reply(reply: dict) -> None:
            stamp_s = time.time()
            if reply.get("ok") and reply.get("task"):
                goal = Goal(uuid, act.verb, stamp_s, time.monotonic(), task=str(reply["task"]))
                self.goals[uuid] = goal
                self.by_task[goal.task] = goal
                self._publish_status(act)
                ended = self._ended.pop(goal.task, None)
                if ended is not None:
                    del self.by_task[goal.task]
                    self._end(goal, ended)
            else:
                self._refuse(uuid, reply)
            answer(response(accepted=bool(reply.get("ok")), stamp=M.ros_time(ts, stamp_s)))
        key = self.node.intake.keys.cmd(act.verb)
        self.node.intake.handle(_Call(key, payload, on_reply), key, payload, now, charged=True)

    def _refuse(self, uuid: bytes, reply: dict) -> None:
        self.refused[uuid] = _result(reply)
        while len(self.refused) > MAX_REFUSED:
            self.refused.popitem(last=False)

    def _cancel(self, act: _Action, req, answer, now: float) -> None:
        """rcl_action's selection: a goal id (zeros: none) and a stamp (zero: none); every goal of this action
        accepted at or before the stamp, and the one named. Those still running are cancelled through the intake."""
        ts = self.node.ts
        uuid = bytes(req.goal_info.goal_id.uuid)
        stamp_s = req.goal_info.stamp.sec + req.goal_info.stamp.nanosec * 1e-9
        mine = [g for g in self.goals.values() if g.verb == act.verb]
        if not any(uuid) and stamp_s == 0.0:
            chosen = mine
        else:
            chosen = [g for g in mine if (any(uuid) and g.uuid == uuid) or (stamp_s > 0.0 and g.stamp_s <= stamp_s)]
        running = [g for g in chosen if g.status not in ENDED]
        response = ts.cls(CANCEL_GOAL + "_Response")
        if not running:
            named = self.goals.get(uuid)
            code = ERROR_UNKNOWN_GOAL_ID if any(uuid) and named is None else \
                ERROR_GOAL_TERMINATED if named is not None and named.status in ENDED else ERROR_REJECTED
            answer(response(return_code=code, goals_canceling=[]))
            return
        key = self.node.intake.keys.cmd("cancel")
        for goal in running:
            goal.status = CANCELING
            payload = json.dumps({"task": goal.task}).encode()
            self.node.intake.handle(_Call(key, payload, lambda reply: None), key, payload, now, charged=True)
        self._publish_status(act)
        info = ts.cls("action_msgs/msg/GoalInfo")
        answer(response(return_code=ERROR_NONE, goals_canceling=[
            info(goal_id=_uuid(ts, g.uuid), stamp=M.ros_time(ts, g.stamp_s)) for g in running]))

    def _get_result(self, act: _Action, uuid: bytes, query, seq: int, client_gid: bytes, answer) -> None:
        goal = self.goals.get(uuid)
        if goal is None or goal.verb != act.verb:
            refused = self.refused.get(uuid)
            answer(self._result_response(act, UNKNOWN if refused is None else ABORTED, refused or _result({})))
        elif goal.status in ENDED:
            answer(self._result_response(act, goal.status, goal.result))
        elif len(goal.waiting) < MAX_WAITING:
            goal.waiting.append((query, seq, client_gid))     # answered when the task ends
        else:
            # a flood of result requests for one goal holds no more than MAX_WAITING queries open: the rest are
            # answered at once with the goal's status as it stands and an empty result
            answer(self._result_response(act, goal.status, _result({"task": goal.task})))

    def _result_response(self, act: _Action, status: int, result: dict):
        ts = self.node.ts
        return ts.cls(act.types.get_result.response)(status=status, result=ts.cls(act.types.result)(**result))

    # -- the daemon's messages (the main thread) ---------------------------------------------------------
    def on_telemetry(self, kind: str, body: dict) -> None:
        if kind == "event" and body.get("kind") in ("task_done", "task_failed"):
            task = str(body.get("task"))
            goal = self.by_task.pop(task, None)
            if goal is not None:
                self._end(goal, body)
            else:
                # a task whose acceptance the intake has not yet handed back (a task shorter than that hand-over)
                self._ended[task] = body
                while len(self._ended) > MAX_REFUSED:
                    self._ended.popitem(last=False)
        elif kind == "state" and self.by_task:
            self._feedback(body)

    def _end(self, goal: Goal, event: dict) -> None:
        error = str(event.get("error") or "")
        if event["kind"] == "task_done":
            goal.status, code = SUCCEEDED, ""
        elif error == "cancelled":
            goal.status, code = CANCELED, "cancelled"
        else:
            goal.status, code = ABORTED, "protective_stop" if error.startswith("protective stop") else "task_failed"
        result = event.get("result")
        goal.result = dict(ok=goal.status == SUCCEEDED, task=goal.task, error_code=code, error_message=error,
                           result_json=json.dumps(result, separators=(",", ":")) if result is not None else "")
        goal.ended_t = time.monotonic()
        act = self._action(goal.verb)
        msg = self._result_response(act, goal.status, goal.result)
        payload = self.node.ts.encode(msg, act.types.get_result.response)
        for query, seq, client_gid in goal.waiting:
            try:
                query.reply(query.key_expr, payload, attachment=rmw.attachment(seq, time.time_ns(), client_gid))
            except Exception:
                log.debug("ROS 2: a held get_result's client has gone", exc_info=True)
        goal.waiting.clear()      # dropping the queries ends them
        self._publish_status(act)

    def _feedback(self, state: dict) -> None:
        task = state.get("task") or {}
        goal = self.by_task.get(str(task.get("id")))
        if goal is None:
            return
        tcp_p = (state.get("tcp") or {}).get("p")
        if goal.start_p is None:
            goal.start_p = tcp_p
        now = time.monotonic()
        act = self._action(goal.verb)
        if now - goal.feedback_t < FEEDBACK_PERIOD_S or not matching(act.feedback[0]):
            return
        goal.feedback_t = now
        ts = self.node.ts
        contact = state.get("contact") or {}
        valid = bool(contact) and (contact.get("onset_t") or -math.inf) >= goal.t_accepted - ONSET_SLACK_S
        travel = math.dist(tcp_p, goal.start_p) if tcp_p and goal.start_p else 0.0
        P, V = ts.cls("geometry_msgs/msg/Point"), ts.cls("geometry_msgs/msg/Vector3")
        p = contact.get("p") if valid else None
        axis = contact.get("axis") if valid else None
        std = contact.get("std") if valid else None
        feedback = ts.cls(act.types.feedback)(
            task=goal.task, phase=str(task.get("phase", "")), progress=float(task.get("progress") or 0.0),
            travel_m=travel, angle_deg=float(contact["angle_deg"]) if valid and contact.get("angle_deg") is not None
            else math.nan, contact_valid=valid,
            contact_point=P(x=float(p[0]), y=float(p[1]), z=float(p[2])) if p else P(x=0.0, y=0.0, z=0.0),
            contact_axis=V(x=float(axis[0]), y=float(axis[1]), z=float(axis[2])) if axis else V(x=0.0, y=0.0, z=0.0),
            contact_std_m=_array3(std))
        msg = ts.cls(act.types.feedback_message)(goal_id=_uuid(ts, goal.uuid), feedback=feedback)
        self._put(act.feedback, msg, act.types.feedback_message)

    # -- status ---------------------------------------------------------------------------------------------
    def _publish_status(self, act: _Action) -> None:
        ts = self.node.ts
        status, info = ts.cls("action_msgs/msg/GoalStatus"), ts.cls("action_msgs/msg/GoalInfo")
        goals = [status(goal_info=info(goal_id=_uuid(ts, g.uuid), stamp=M.ros_time(ts, g.stamp_s)), status=g.status)
                 for g in self.goals.values() if g.verb == act.verb]
        self._put(act.status, ts.cls(GOAL_STATUS_ARRAY)(status_list=goals), GOAL_STATUS_ARRAY)

    def _put(self, pub: tuple, msg, ros_type: str) -> None:
        publisher, gid, seq = pub
        seq[0] += 1
        try:
            publisher.put(self.node.ts.encode(msg, ros_type), attachment=rmw.attachment(seq[0], time.time_ns(), gid))
            self.node.counters["published"] += 1
        except Exception:
            log.exception("ROS 2: a %s was not published", ros_type)

    def _expire(self, now: float) -> None:
        """Ended goals older than RESULT_TIMEOUT_S, and the oldest ended ones past MAX_GOALS, forgotten."""
        t = time.monotonic()
        ended = [g for g in self.goals.values() if g.status in ENDED]
        old = [g for g in ended if t - g.ended_t > RESULT_TIMEOUT_S]
        excess = len(self.goals) - len(old) - MAX_GOALS
        if excess > 0:
            old += [g for g in ended if g not in old][:excess]
        for goal in old:
            del self.goals[goal.uuid]
        for verb in {g.verb for g in old}:
            self._publish_status(self._action(verb))


def _result(reply: dict) -> dict:
    """A Result's fields of a Zenoh reply (a refusal's code and message)."""
    err = reply.get("error") or {}
    return dict(ok=bool(reply.get("ok")), task=str(reply.get("task", "") or ""), error_code=str(err.get("code", "")),
                error_message=str(err.get("message", "")), result_json="")


def _uuid(ts, raw: bytes):
    import numpy as np
    return ts.cls("unique_identifier_msgs/msg/UUID")(uuid=np.frombuffer(raw, dtype=np.uint8).copy())


def _array3(values) -> "object":
    import numpy as np
    out = np.full(3, math.nan)
    if values:
        out[:] = [float(v) for v in values[:3]]
    return out


def matching(publisher) -> bool:
    """Whether anyone subscribes to what `publisher` puts (Zenoh's matching status, about 1 µs; True when it cannot
    say): a message nobody takes is neither built nor encoded."""
    try:
        return bool(publisher.matching_status.matching)
    except Exception:
        return True
