"""Fuzz tier for the ROS 2 node (issue 36): every service request and every JointState on the wire is
untrusted. Hypothesis-generated CDR (valid requests with hostile values, truncated and random bytes,
huge sequences) and attachments go through the node's real request path (Ros2Node._call, then the
daemon's QueryIntake) and its joint-state path (the node's decoding, then the observer backend).
Whatever comes: nothing raises, a request is answered at most once (an error reply with a known code)
or handed to the control thread within the configured limits, and a joint state is a new state or a
fault, never a state that fails the checks."""
import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tecdard.api import commands as C
from tecdard.api.session import Keys
from tecdard.runtime.intake import IntakeParams, QueryIntake
from tecdard.runtime.messages import StartTask

pytest.importorskip("rosbags", reason="rosbags is installed by `make test` (extra ros2)")
from tecdard.ros2 import rmw  # noqa: E402
from tecdard.runtime.ros2_node import Ros2Node, Ros2Params, _Service  # noqa: E402
from tecdard.runtime.ros2_subscribe import JOINT_STATE, subscribe  # noqa: E402
from tests.test_fuzz_commands import CODES, LIMITS, Sink  # noqa: E402

CODES = CODES | {C.READ_ONLY}
EXAMPLES = 500
GID = bytes(range(16))


def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


class ZBytes:
    """zenoh.ZBytes as the node uses it: its bytes and its length."""

    def __init__(self, raw):
        self.raw = raw

    def to_bytes(self):
        return self.raw

    def __len__(self):
        return len(self.raw)


class RosQuery:
    """A Zenoh query as the node receives it: CDR payload, attachment, and its replies recorded."""

    def __init__(self, payload: bytes, attachment: bytes | None):
        self.payload = ZBytes(payload)
        self.attachment = None if attachment is None else ZBytes(attachment)
        self.key_expr = "0/sim/x/t/h"
        self.replies = []

    def reply(self, key, payload, attachment=None):
        self.replies.append((bytes(payload), bytes(attachment)))


@pytest.fixture(scope="module")
def node():
    n = Ros2Node(Ros2Params(enabled=True), "sim", None)
    return n


def serve(node, verb: str, srv_type: str, query: RosQuery, read_only=None):
    sink = Sink()
    intake = QueryIntake(Keys("sim"), LIMITS, sink, lambda: '{"mode":"idle"}', IntakeParams(max_task_rate_hz=1e4,
                         max_status_rate_hz=1e4, max_other_rate_hz=1e4), read_only=read_only)
    node.intake = intake
    svc = _Service(verb, srv_type, "key")
    call = node._call(svc, query)
    if call is not None:
        intake.handle(call, call.key_expr, call.payload, 0.0)
    return sink


def check_reply(node, srv_type: str, query: RosQuery, sink) -> int:
    """At most one reply, a response of the service's type with the request's sequence number and GID,
    and a refusal with a known code and one short line; or the command handed on, within limits.
    Returns how many outcomes there were (0 or 1)."""
    outcomes = len(query.replies) + len(sink.submitted)
    assert outcomes <= 1
    if query.replies:
        payload, att = query.replies[0]
        seq, _t, gid = rmw.parse_attachment(att)
        assert gid == GID
        res = node.ts.decode(payload, srv_type + "_Response")
        if not res.ok:
            assert res.error_code in CODES and "\n" not in res.error_message and len(res.error_message) < 400
    for msg in sink.submitted:
        assert isinstance(msg, StartTask)
        for v in msg.fields.values():
            for x in (v if isinstance(v, list) else [v]):
                assert not isinstance(x, float) or math.isfinite(x)
        if "speed" in msg.fields:
            assert LIMITS.min_speed <= msg.fields["speed"] <= LIMITS.max_speed
    return outcomes


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
arrays = st.lists(floats, max_size=8)


@pytest.mark.slow
@fuzz_settings(EXAMPLES)
@given(angle=floats, speed=floats, probe=floats, direction=arrays, strategy=st.text(max_size=40),
       turn=st.integers(0, 255), seq=st.integers(-2**63, 2**63 - 1))
def test_any_rotate_request_is_refused_with_a_code_or_handed_on_within_limits(node, angle, speed, probe, direction,
                                                                             strategy, turn, seq):
    req = node.ts.cls("tecdar_msgs/srv/Rotate_Request")(angle_deg=angle, speed=speed, probe_distance=probe,
                                                         direction=np.array(direction, float), strategy=strategy,
                                                         turn_tool=turn)
    raw = node.ts.encode(req, "tecdar_msgs/srv/Rotate_Request")
    q = RosQuery(raw, rmw.attachment(seq, 0, GID))
    sink = serve(node, "rotate", "tecdar_msgs/srv/Rotate", q)
    assert check_reply(node, "tecdar_msgs/srv/Rotate", q, sink) == 1      # a request with its attachment: answered
    if q.replies:
        assert rmw.parse_attachment(q.replies[0][1])[0] == seq


@pytest.mark.slow
@fuzz_settings(EXAMPLES)
@given(grid=st.lists(st.integers(-2**31, 2**31 - 1), max_size=6), origin=arrays, size=arrays, depth=floats,
       speed=floats, orientations=st.integers(0, 255))
def test_any_map_request_is_refused_with_a_code_or_handed_on_within_limits(node, grid, origin, size, depth, speed,
                                                                          orientations):
    req = node.ts.cls("tecdar_msgs/srv/Map_Request")(grid=np.array(grid, np.int32), orientations=orientations,
                                                      origin=np.array(origin, float), size=np.array(size, float),
                                                      depth=depth, speed=speed)
    q = RosQuery(node.ts.encode(req, "tecdar_msgs/srv/Map_Request"), rmw.attachment(1, 0, GID))
    assert check_reply(node, "tecdar_msgs/srv/Map", q, serve(node, "map", "tecdar_msgs/srv/Map", q)) == 1


@pytest.mark.slow
@fuzz_settings(EXAMPLES)
@given(raw=st.binary(max_size=300), cut=st.integers(0, 200), att=st.one_of(st.none(), st.binary(max_size=40)))
def test_random_truncated_bytes_and_attachments_never_raise(node, raw, cut, att):
    valid = node.ts.encode(node.ts.cls("tecdar_msgs/srv/Probe_Request")(
        direction=np.array([0.0, 0.0, 1.0]), distance=0.005, speed=0.01), "tecdar_msgs/srv/Probe_Request")
    bad_attachment = att is not None and len(att) != rmw.ATTACHMENT_BYTES
    for payload in (raw, valid[:cut], b"\x00\x01\x00\x00" + raw):
        q = RosQuery(payload, att if bad_attachment else rmw.attachment(1, 0, GID))
        sink = serve(node, "probe", "tecdar_msgs/srv/Probe", q)
        # no attachment a client would send: no reply; with one, exactly one answer or hand-over
        assert check_reply(node, "tecdar_msgs/srv/Probe", q, sink) == (0 if bad_attachment else 1)


def test_a_huge_sequence_is_refused_unread_and_a_bad_attachment_unanswered(node):
    req = node.ts.cls("tecdar_msgs/srv/Probe_Request")(direction=np.zeros(300_000), distance=0.005, speed=0.01)
    q = RosQuery(node.ts.encode(req, "tecdar_msgs/srv/Probe_Request"), rmw.attachment(9, 0, GID))
    sink = serve(node, "probe", "tecdar_msgs/srv/Probe", q)
    assert not sink.submitted
    res = node.ts.decode(q.replies[0][0], "tecdar_msgs/srv/Probe_Response")
    assert res.error_code == C.PAYLOAD_TOO_LARGE
    for att in (None, b"", GID, rmw.attachment(1, 0, GID)[:-1]):
        q = RosQuery(b"\x00\x01\x00\x00", att)
        assert not serve(node, "probe", "tecdar_msgs/srv/Probe", q).submitted and q.replies == []
    q = RosQuery(node.ts.encode(node.ts.cls("tecdar_msgs/srv/Probe_Request")(direction=np.zeros(0), distance=math.nan,
                                                                             speed=math.nan),
                                "tecdar_msgs/srv/Probe_Request"), rmw.attachment(2, 0, GID))
    sink = serve(node, "probe", "tecdar_msgs/srv/Probe", q, read_only="observed")
    assert not sink.submitted
    assert node.ts.decode(q.replies[0][0], "tecdar_msgs/srv/Probe_Response").error_code == C.READ_ONLY


# -- joint states --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def observer():
    from tecdard.config import Config
    from tecdard.robots.backends import BackendContext
    from tecdard.robots.model import READY_Q, ArmModel
    from tecdard.robots.ros2_observer import Ros2Observer
    return Ros2Observer(BackendContext(Config({}), ArmModel("panda"), np.array(READY_Q["panda"]), [0, 0, 0, 1]))


PANDA = [f"panda_joint{i}" for i in range(1, 8)]


@pytest.mark.slow
@fuzz_settings(EXAMPLES)
@given(names=st.lists(st.sampled_from(PANDA + ["", "x", "panda_finger_joint1"]), max_size=10),
       position=st.lists(floats, max_size=10), velocity=st.lists(floats, max_size=10),
       sec=st.integers(-2**31, 2**31 - 1), nsec=st.integers(0, 2**32 - 1), raw=st.binary(max_size=200),
       cut=st.integers(0, 400))
def test_any_joint_state_is_a_checked_state_or_a_fault(node, observer, names, position, velocity, sec, nsec, raw, cut):
    T = node.ts.store.types
    msg = T["sensor_msgs/msg/JointState"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=""),
        name=names, position=np.array(position, float), velocity=np.array(velocity, float), effort=np.zeros(0))
    valid = node.ts.encode(msg, "sensor_msgs/msg/JointState")
    for payload in (valid, valid[:cut], raw):
        seq = observer.read_state().seq
        try:
            decoded, problem = node.ts.decode(payload, "sensor_msgs/msg/JointState"), None
        except ValueError as exc:
            decoded, problem = None, str(exc)
        observer.on_joint_state(decoded, problem)
        js = observer.read_state()
        if js.seq != seq:              # a new state: it passed every check
            check = observer.state_check
            assert math.isfinite(js.t) and js.q.shape == (7,) and np.all(np.isfinite(js.q))
            assert np.all(js.q >= check.q_min) and np.all(js.q <= check.q_max)


def test_a_flood_of_large_ros2_requests_is_charged_before_it_is_decoded(node):
    """Issue 50 item 1: two clients sent 1.9 MB `Map` requests for 5 s and the daemon froze: the node decoded
    each request's CDR into Python objects before the intake saw its size or its class's budget. Now a request
    over the size limit is refused unread, and one beyond the class's rate is refused before it is decoded."""
    sink = Sink()
    intake = QueryIntake(Keys("sim"), LIMITS, sink, lambda: '{"mode":"idle"}', IntakeParams(max_task_rate_hz=5.0))
    node.intake = intake
    svc = _Service("map", "tecdar_msgs/srv/Map", "key")
    decoded = []
    real = node.ts.decode
    node.ts.decode = lambda raw, t: decoded.append(len(raw)) or real(raw, t)
    try:
        req = node.ts.cls("tecdar_msgs/srv/Map_Request")(
            origin=np.zeros(0), size=np.zeros(0), grid=np.arange(480_000, dtype=np.int32), depth=0.0, speed=0.0,
            orientations=0)
        huge = node.ts.encode(req, "tecdar_msgs/srv/Map_Request")
        assert len(huge) > 1_900_000
        t0 = time.monotonic()                                                # the intake's clock
        queries = [RosQuery(huge, rmw.attachment(k, 0, GID)) for k in range(50)]
        for k, q in enumerate(queries):
            assert node._call(svc, q, now=t0 + k * 0.01) is None            # refused: too large, or over the rate
        assert decoded == []                                                  # none decoded
        codes = [real(q.replies[0][0], "tecdar_msgs/srv/Map_Response") for q in queries if q.replies]
        assert codes and {r.error_code for r in codes} <= {C.PAYLOAD_TOO_LARGE, C.RATE_LIMITED}
        assert any(r.error_code == C.PAYLOAD_TOO_LARGE for r in codes)
        # small requests beyond the task class's 5 a second: refused before they are decoded
        small = node.ts.encode(node.ts.cls("tecdar_msgs/srv/Map_Request")(
            origin=np.zeros(0), size=np.zeros(0), grid=np.zeros(0, np.int32), depth=0.0, speed=0.0,
            orientations=0), "tecdar_msgs/srv/Map_Request")
        decoded.clear()
        for k in range(40):
            call = node._call(svc, RosQuery(small, rmw.attachment(k, 0, GID)), now=t0 + 10.0)
            if call is not None:
                intake.handle(call, call.key_expr, call.payload, t0 + 10.0, charged=True)
        assert 0 < len(decoded) <= 10 and intake.counters["rate_limited"] + intake.counters["dropped"] >= 30
    finally:
        node.ts.decode = real


def test_joint_states_are_decimated_to_the_tick_before_they_are_decoded(node, observer):
    """Issue 51 item 4: every /joint_states message was decoded and checked on Zenoh's thread, so a 1 kHz driver cost
    twenty times a 50 Hz one. The subscription drops a message within min_period_s (half the control tick) of the
    last one taken, undecoded: at 1 kHz for 0.3 s about 30 are handed on, not 300; at 50 Hz, all."""
    import types
    T = node.ts.store.types
    msg = T["sensor_msgs/msg/JointState"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id=""),
        name=PANDA, position=np.array(observer.read_state().q, float), velocity=np.zeros(7), effort=np.zeros(0))
    sample = types.SimpleNamespace(payload=_Payload(node.ts.encode(msg, "sensor_msgs/msg/JointState")),
                                   attachment=None)
    assert observer.topic_state.min_period_s == pytest.approx(0.010)       # half the default 20 ms tick
    subscribed = {}
    node.session = types.SimpleNamespace(declare_subscriber=lambda key, cb: subscribed.setdefault("cb", cb))
    node._entity = lambda *a: ("key", None)
    try:
        for period_s, n in ((0.001, 300), (0.02, 15)):
            taken: list = []
            subscribed.clear()
            subscribe(node, "/joint_states", JOINT_STATE, lambda m, problem, source=None: taken.append(m),
                      "joint_states", observer.topic_state.min_period_s)
            t_next = time.monotonic()
            for _ in range(n):
                subscribed["cb"](sample)
                t_next += period_s
                time.sleep(max(0.0, t_next - time.monotonic()))
            assert all(m is not None for m in taken)
            if period_s == 0.001:
                assert 15 <= len(taken) <= 45, len(taken)
            else:
                assert len(taken) >= n - 1, len(taken)        # a 50 Hz driver loses nothing (its jitter aside)
    finally:
        del node._entity
        node._declared.clear()


class _Payload:
    """A Zenoh payload as the subscription reads it."""

    def __init__(self, data: bytes):
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


@pytest.mark.slow
@fuzz_settings(200)
@given(raw=st.binary(max_size=300), cut=st.integers(0, 400), names=st.lists(st.text(max_size=40), max_size=20))
def test_any_parameter_or_type_request_is_one_reply_or_none_and_never_raises(node, raw, cut, names):
    """Issue 51 item 6: the new front doors (the parameter services, ~/get_type_description) take any bytes: each
    request gets one reply of its service's type or none, and never raises into the main loop."""
    from tecdard.ros2 import parameters as P
    from tecdard.ros2 import type_description as TD
    from tecdard.runtime.option_sections import sections
    from tecdard.runtime.ros2_parameters import ParameterServer, _Service as PService
    from tests.conftest import SIM_CONFIG
    import yaml
    server = _parameter_server(node, ParameterServer, P, TD, sections, SIM_CONFIG, yaml)
    T = node.ts.store.types
    valid = node.ts.encode(T["rcl_interfaces/srv/GetParameters_Request"](names=names),
                           "rcl_interfaces/srv/GetParameters_Request")
    for srv_type in (*P.SERVICES.values(), TD.SERVICE):
        for payload in (valid, valid[:cut], raw):
            q = RosQuery(payload, rmw.attachment(5, 0, GID))
            server._answer(PService("x", srv_type, "key"), q, 0.0)
            assert len(q.replies) <= 1
            if q.replies:
                reply, att = q.replies[0]
                assert rmw.parse_attachment(att)[0] == 5
                node.ts.decode(reply, srv_type + "_Response")


def test_a_parameter_request_naming_100_000_names_is_answered_for_none_and_a_flood_is_budgeted(node):
    from tecdard.ros2 import parameters as P
    from tecdard.ros2 import type_description as TD
    from tecdard.runtime.option_sections import sections
    from tecdard.runtime.ros2_parameters import ParameterServer, _Service as PService
    from tests.conftest import SIM_CONFIG
    import yaml
    server = _parameter_server(node, ParameterServer, P, TD, sections, SIM_CONFIG, yaml)
    T = node.ts.store.types
    huge = node.ts.encode(T["rcl_interfaces/srv/GetParameters_Request"](names=["control.max_force_n"] * 100_000),
                          "rcl_interfaces/srv/GetParameters_Request")
    q = RosQuery(huge, rmw.attachment(1, 0, GID))
    server._answer(PService("get_parameters", "rcl_interfaces/srv/GetParameters", "key"), q, 0.0)
    # 1.4 MB: over the intake's payload limit, refused unread (no reply: these services have no error field)
    assert q.replies == [] or node.ts.decode(q.replies[0][0], "rcl_interfaces/srv/GetParameters_Response").values == []
    small = node.ts.encode(T["rcl_interfaces/srv/GetParameters_Request"](names=["control.max_force_n"]),
                           "rcl_interfaces/srv/GetParameters_Request")
    answered = 0
    for k in range(200):                 # 200 at one instant: the status class's budget answers a burst, not all
        q = RosQuery(small, rmw.attachment(k, 0, GID))
        server._answer(PService("get_parameters", "rcl_interfaces/srv/GetParameters", "key"), q, 1.0)
        answered += len(q.replies)
    assert 0 < answered < 200, answered


def _parameter_server(node, ParameterServer, P, TD, sections, SIM_CONFIG, yaml):
    """The node's parameter server as the daemon makes it, on an intake whose status class allows 50 a second."""
    for srv_type, text in P.SRV_TEXTS.items():
        node.ts.add_service(text, srv_type)
    node.ts.add_service(TD.SRV_TEXT, TD.SERVICE)
    node.intake = QueryIntake(Keys("sim"), LIMITS, Sink(), lambda: '{"mode":"idle"}',
                              IntakeParams(max_status_rate_hz=50.0))
    node.types_in_use = {"tecdar_msgs/srv/Rotate": node.ts.type_hash("tecdar_msgs/srv/Rotate")}
    return ParameterServer(node, P.ParameterSet(yaml.safe_load(SIM_CONFIG.read_text()), sections()))


class _Unheard:
    """A publisher nobody listens to (the action server's status and feedback, off a session)."""

    def put(self, *_args, **_kwargs) -> None:
        pass


def _rotate_action_server(node):
    """The node's action server for `rotate` alone, without a session: (server, its action, the type store's
    classes). Its status and feedback go nowhere."""
    from tecdard.ros2.typesupport import CANCEL_GOAL, CANCEL_GOAL_SRV
    from tecdard.runtime.ros2_actions import ActionServer, _Action
    node.ts.add_service(CANCEL_GOAL_SRV, CANCEL_GOAL)
    server = ActionServer(node)
    act = _Action("rotate", node.ts.actions["tecdar_msgs/action/Rotate"])
    act.status, act.feedback = (_Unheard(), GID, [0]), (_Unheard(), GID, [0])
    server.actions.append(act)
    return server, act, node.ts.store.types


def _rotate_goal(T, types, angle_deg: float, direction=()):
    return T[types.goal](angle_deg=angle_deg, speed=math.nan, probe_distance=math.nan,
                         direction=np.array(direction, dtype=float), strategy="", turn_tool=0)


@pytest.mark.slow
@fuzz_settings(200)
@given(raw=st.binary(max_size=300), cut=st.integers(0, 400), angle=floats, direction=arrays,
       uuid=st.binary(min_size=16, max_size=16), stamp=st.integers(0, 2**31 - 1))
def test_any_action_request_is_one_reply_or_none_and_a_goal_is_handed_on_within_limits(node, raw, cut, angle,
                                                                                      direction, uuid, stamp):
    """Issue 51 item 6 for the actions (tecdard/runtime/ros2_actions.py): a send_goal, cancel_goal or get_result of
    any bytes gets one reply of its service's type or none and never raises; a goal the intake takes is handed on
    within the limits, one it refuses is not accepted."""
    from tecdard.ros2.typesupport import CANCEL_GOAL
    sink = Sink()
    node.intake = QueryIntake(Keys("sim"), LIMITS, sink, lambda: '{"mode":"idle"}', IntakeParams(
        max_task_rate_hz=1e4, max_status_rate_hz=1e4, max_other_rate_hz=1e4))
    server, act, T = _rotate_action_server(node)
    types = act.types
    uuid_msg = T["unique_identifier_msgs/msg/UUID"](uuid=np.frombuffer(uuid, dtype=np.uint8).copy())
    goal = _rotate_goal(T, types, angle, direction)
    send = node.ts.encode(T[types.send_goal.request](goal_id=uuid_msg, goal=goal), types.send_goal.request)
    result = node.ts.encode(T[types.get_result.request](goal_id=uuid_msg), types.get_result.request)
    info = T["action_msgs/msg/GoalInfo"](goal_id=uuid_msg, stamp=T["builtin_interfaces/msg/Time"](sec=stamp, nanosec=0))
    cancel = node.ts.encode(T[CANCEL_GOAL + "_Request"](goal_info=info), CANCEL_GOAL + "_Request")
    for name, srv_type, valid in (("send_goal", types.send_goal.name, send), ("get_result", types.get_result.name,
                                  result), ("cancel_goal", CANCEL_GOAL, cancel)):
        for payload in (valid, valid[:cut], raw):
            before = len(sink.submitted)
            q = RosQuery(payload, rmw.attachment(9, 0, GID))
            server._request(act, name, q, 0.0)
            assert len(q.replies) <= 1
            if q.replies:
                reply, att = q.replies[0]
                assert rmw.parse_attachment(att)[:3:2] == (9, GID)
                res = node.ts.decode(reply, srv_type + "_Response")
                if name == "send_goal":
                    # accepted only once the control thread's reply says so (the sink never replies)
                    assert res.accepted is False
            for msg in sink.submitted[before:]:
                assert isinstance(msg, StartTask) and name == "send_goal" and payload is valid
                assert 0.0 < msg.fields["angle_deg"] <= LIMITS.max_rotation_deg
                assert all(math.isfinite(x) for x in msg.fields.get("direction", []))


def test_a_goal_flood_is_charged_before_it_is_decoded_and_buys_no_more_than_the_task_verbs_budget(node):
    """Issue 51 item 6: 200 rotate goals at one instant through send_goal, on the daemon's default budgets: the task
    verbs' burst reaches the control thread, the rest is refused before decoding (not accepted, or dropped once the
    refusals' own budget is spent), and no goal is accepted without the control thread's reply."""
    sink = Sink()
    node.intake = QueryIntake(Keys("sim"), LIMITS, sink, lambda: '{"mode":"idle"}', IntakeParams())
    server, act, T = _rotate_action_server(node)
    types = act.types
    answered = 0
    for k in range(200):
        uuid = T["unique_identifier_msgs/msg/UUID"](uuid=np.full(16, k % 256, dtype=np.uint8))
        goal = _rotate_goal(T, types, 10.0)
        q = RosQuery(node.ts.encode(T[types.send_goal.request](goal_id=uuid, goal=goal), types.send_goal.request),
                     rmw.attachment(k, 0, GID))
        server._request(act, "send_goal", q, 5.0)
        for reply, _att in q.replies:
            answered += 1
            assert node.ts.decode(reply, types.send_goal.response).accepted is False
    burst = max(IntakeParams().max_task_rate_hz, 5.0)          # a second of the class's rate, saved up
    assert 0 < len(sink.submitted) <= burst, len(sink.submitted)
    assert len(sink.submitted) + answered <= 200 and not server.goals


def test_result_requests_for_a_running_goal_hold_at_most_64_queries_open(node):
    """A flood of get_result for one running goal: 64 held until the task ends, the rest answered at once with the
    goal's status (EXECUTING); the task's end answers the held ones with its result."""
    import time as _time
    from tecdard.runtime.ros2_actions import EXECUTING, MAX_WAITING, SUCCEEDED, Goal
    node.intake = QueryIntake(Keys("sim"), LIMITS, Sink(), lambda: '{"mode":"idle"}', IntakeParams(
        max_status_rate_hz=1e4))
    server, act, T = _rotate_action_server(node)
    uuid = bytes(range(16))
    goal = Goal(uuid, "rotate", _time.time(), _time.monotonic(), task="rotate-1")
    server.goals[uuid], server.by_task["rotate-1"] = goal, goal
    types = act.types
    req = node.ts.encode(T[types.get_result.request](goal_id=T["unique_identifier_msgs/msg/UUID"](
        uuid=np.frombuffer(uuid, dtype=np.uint8).copy())), types.get_result.request)
    queries = [RosQuery(req, rmw.attachment(k, 0, GID)) for k in range(200)]
    for q in queries:
        server._request(act, "get_result", q, 1.0)
    early = [node.ts.decode(q.replies[0][0], types.get_result.response) for q in queries if q.replies]
    assert len(goal.waiting) == MAX_WAITING and len(early) == 200 - MAX_WAITING
    assert all(r.status == EXECUTING for r in early)
    server.on_telemetry("event", {"kind": "task_done", "task": "rotate-1", "result": {"angle_deg": 20.0}})
    held = [node.ts.decode(q.replies[0][0], types.get_result.response) for q in queries[:MAX_WAITING]]
    assert all(r.status == SUCCEEDED and r.result.ok for r in held) and not goal.waiting


def test_a_task_that_ends_before_its_acceptance_is_handed_back_still_ends_its_goal(node):
    """The task's end event reaches the node before the intake hands back its acceptance: the goal is accepted,
    already ended, and its result is there (no get_result left waiting forever)."""
    import json as _json
    from tecdard.runtime.ros2_actions import SUCCEEDED

    class Intake:
        keys = Keys("sim")

        def charge(self, *_a):
            return True

        def handle(self, call, _key, _payload, _now, charged=False):
            server.on_telemetry("event", {"kind": "task_done", "task": "rotate-9", "result": {"angle_deg": 1.0}})
            call.reply(None, _json.dumps({"ok": True, "task": "rotate-9"}))
    node.intake = Intake()
    server, act, T = _rotate_action_server(node)
    types = act.types
    uuid = T["unique_identifier_msgs/msg/UUID"](uuid=np.arange(16, dtype=np.uint8))
    goal = _rotate_goal(T, types, 10.0)
    q = RosQuery(node.ts.encode(T[types.send_goal.request](goal_id=uuid, goal=goal), types.send_goal.request),
                 rmw.attachment(1, 0, GID))
    server._request(act, "send_goal", q, 1.0)
    assert node.ts.decode(q.replies[0][0], types.send_goal.response).accepted is True
    (only,) = server.goals.values()
    assert only.status == SUCCEEDED and _json.loads(only.result["result_json"]) == {"angle_deg": 1.0}
    assert not server.by_task
