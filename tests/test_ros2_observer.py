"""`robot.backend: ros2` on its own (issue 36): joint states matched by name, stamped on the daemon's clock,
the TCP from our FK, and faults (never a wrong TCP) for streams that stop, jump, lack a joint or lie;
a user's URDF that cannot be the arm is one line."""
import math
import threading
import time

import numpy as np
import pytest

from tecdard.config import Config
from tecdard.robots.backends import BackendContext, ModelMismatch
from tecdard.robots.model import READY_Q, ArmModel, UnknownRobotError
from tecdard.robots.ros2_observer import FAULT, Ros2Observer

pytest.importorskip("rosbags", reason="rosbags is installed by `make test` (extra ros2)")
from tecdard.ros2.typesupport import TypeSupport   # noqa: E402

PANDA = [f"panda_joint{i}" for i in range(1, 8)]
Q = np.array(READY_Q["panda"])
FK_TOL_M = 1e-9
STATE_DT_S = 0.002


@pytest.fixture(scope="module")
def ts():
    return TypeSupport()


@pytest.fixture
def observer():
    model = ArmModel("panda")
    cfg = Config({"robot": {"ros2": {"stale_s": 0.1, "first_state_s": 0.3}}})
    return Ros2Observer(BackendContext(cfg, model, Q.copy(), [0, 0, 0, 1]))


def joint_state(ts, names, q, qd=None, stamp_s=None):
    t = time.time() if stamp_s is None else stamp_s
    ns = int(round(t * 1e9))
    T = ts.store.types
    return T["sensor_msgs/msg/JointState"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=""),
        name=list(names), position=np.asarray(q, float),
        velocity=np.zeros(0) if qd is None else np.asarray(qd, float), effort=np.zeros(0))


def test_names_in_any_order_make_the_models_state_and_its_tcp(ts, observer):
    order = [6, 0, 5, 1, 4, 2, 3]
    names = [PANDA[i] for i in order] + ["panda_finger_joint1"]
    observer.on_joint_state(joint_state(ts, names, list(Q[order]) + [0.04], list(np.arange(7.0)[order] * 0.01) + [0]),
                            None)
    js = observer.read_state()
    assert js.seq == 1 and np.allclose(js.q, Q) and np.allclose(js.qd, np.arange(7.0) * 0.01)
    assert abs(js.t - time.monotonic()) < 0.05
    assert observer.faults() == {}
    fk = observer.model.fk(Q).translation
    assert np.linalg.norm(observer.model.measured(js)[0].translation - fk) < FK_TOL_M


def test_without_velocities_the_rates_come_from_the_positions(ts, observer):
    t0 = time.time() - 0.01
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=t0), None)
    q1 = Q + 0.001
    observer.on_joint_state(joint_state(ts, PANDA, q1, stamp_s=t0 + STATE_DT_S), None)
    assert np.allclose(observer.read_state().qd, 0.001 / STATE_DT_S, rtol=1e-3)


def test_a_gripper_drivers_message_on_the_same_topic_is_skipped(ts, observer):
    observer.on_joint_state(joint_state(ts, ["panda_finger_joint1", "panda_finger_joint2"], [0.01, 0.01]), None)
    assert observer.skipped == 1 and observer.read_state().seq == 0 and observer.faults() == {}


@pytest.mark.parametrize("case, expect", [
    ("missing", "no panda_joint7"),
    ("lengths", "7 names and 6 positions"),
    ("twice", "named twice"),
    ("zero stamp", "stamp is zero"),
    ("future", "in the future"),
    ("undecodable", "do not decode"),
])
def test_a_message_that_cannot_be_the_arms_state_is_a_fault_naming_it(ts, observer, case, expect):
    if case == "missing":
        msg = joint_state(ts, PANDA[:6], Q[:6])
    elif case == "lengths":
        msg = joint_state(ts, PANDA, Q[:6])
    elif case == "twice":
        msg = joint_state(ts, PANDA[:6] + [PANDA[0]], Q)
    elif case == "zero stamp":
        msg = joint_state(ts, PANDA, Q, stamp_s=0.0)
    elif case == "future":
        msg = joint_state(ts, PANDA, Q, stamp_s=time.time() + 3.0)
    if case == "undecodable":
        observer.on_joint_state(None, "sensor_msgs/msg/JointState: 12 bytes that do not decode (SerdeError)")
    else:
        observer.on_joint_state(msg, None)
    assert observer.read_state().seq == 0          # nothing published: never a wrong TCP
    assert expect in observer.faults()[FAULT]


def test_non_finite_out_of_range_and_jumping_joints_are_the_state_checks_fault(ts, observer):
    t0 = time.time() - 0.1
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=t0), None)
    for i, q in enumerate((np.r_[Q[:3], math.nan, Q[4:]], np.r_[Q[:3], 5.0, Q[4:]], Q + np.r_[0.5, np.zeros(6)])):
        observer.on_joint_state(joint_state(ts, PANDA, q, stamp_s=t0 + (i + 1) * STATE_DT_S), None)
        assert observer.read_state().seq == 1
        assert "state refused" in observer.state_faults()["robot_state"]
    assert "jumped" in observer.state_faults()["robot_state"]


def test_a_stream_that_stops_is_stale_after_stale_s(ts, observer):
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=time.time() - 0.2), None)
    js = observer.read_state()
    assert observer.state_age_s == pytest.approx(0.1)
    assert time.monotonic() - observer.state_seen_t(js) > observer.state_age_s     # the control tick's robot_stale


def test_the_observer_never_commands_the_arm(observer):
    assert observer.commands_arm is False and "refused" in observer.read_only_reason
    observer.hold()                                # a protective stop: nothing to do
    observer.command_joint_velocity(np.zeros(7))     # a bug's command: dropped and counted, never raised
    assert observer.commands_dropped == 1


def test_start_waits_for_the_first_state_and_a_stream_of_other_joints_is_a_model_mismatch(ts, observer):
    ur = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
          "wrist_3_joint", "extra_joint"]
    observer.on_joint_state(joint_state(ts, ur, np.zeros(7)), None)
    with pytest.raises(ModelMismatch) as exc:
        observer.start()
    assert "missing: panda_joint1" in str(exc.value) and "robot.model" in str(exc.value)


def test_start_returns_once_the_arm_publishes(ts, observer):
    threading.Timer(0.05, lambda: observer.on_joint_state(joint_state(ts, PANDA, Q), None)).start()
    observer.start()
    assert observer.read_state().seq == 1


URDF = """<robot name="two">
  <link name="base"/><link name="upper"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="upper"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" velocity="2" effort="10"/></joint>
  <joint name="j2" type="revolute"><parent link="upper"/><child link="tool"/><origin xyz="0.3 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" velocity="2" effort="10"/></joint>
</robot>
"""


def test_a_users_urdf_is_the_model_with_its_tcp_link(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(URDF)
    model = ArmModel("urdf:arm.urdf", urdf=str(path), tcp_link="tool")
    assert model.joint_names == ["j1", "j2"] and model.nq == 2
    assert np.allclose(model.fk(np.zeros(2)).translation, [0.3, 0.0, 0.0])


@pytest.mark.parametrize("text, link, expect", [
    ("<robot name='x'><link name=", "tool", "does not parse"),
    ("", "tool", "does not parse"),
    (URDF, "flange", "'flange' is no link"),
    (URDF.replace('type="revolute"', 'type="continuous"', 1), "tool", "not revolute or prismatic"),
    (URDF.replace('velocity="2"', 'velocity="0"', 1), "tool", "no position range or velocity"),
    (URDF, None, "robot.tcp_link: required"),
])
def test_a_urdf_that_cannot_be_the_arm_is_one_line(tmp_path, text, link, expect):
    path = tmp_path / "arm.urdf"
    path.write_text(text)
    with pytest.raises(UnknownRobotError) as exc:
        ArmModel("urdf", urdf=str(path), tcp_link=link)
    assert expect in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(UnknownRobotError, match="no such file"):
        ArmModel("urdf", urdf=str(tmp_path / "none.urdf"), tcp_link="tool")


def test_a_message_with_more_joints_than_an_arm_is_a_fault_and_what_it_names_is_not_kept(ts, observer):
    """Issue 50 item 3: a second publisher sent the model's joints plus 15 000 new names per message; the
    daemon kept and logged every name (122 -> 434 MB in 6 s)."""
    many = PANDA + [f"junk_{k}" for k in range(15000)]
    observer.on_joint_state(joint_state(ts, many, list(Q) + [0.0] * 15000), None)
    assert "15007 joints, more than an arm has" in observer.faults()[FAULT]
    assert observer.read_state().seq == 0 and observer.extra_names == set()


def test_names_beside_the_models_are_remembered_and_logged_only_so_many(ts, observer):
    from tecdard.robots.ros2_observer import MAX_EXTRA_NAMES
    t0 = time.time() - 1.0
    for k in range(5):
        extra = [f"aux_{k}_{j}" for j in range(40)]
        observer.on_joint_state(joint_state(ts, PANDA + extra, list(Q) + [0.0] * 40, stamp_s=t0 + k * STATE_DT_S),
                                None)
    assert observer.read_state().seq == 5 and observer.faults() == {}
    assert len(observer.extra_names) == MAX_EXTRA_NAMES


def test_a_second_publisher_of_the_arms_joints_is_a_fault_and_a_restarted_driver_is_taken(ts, observer):
    driver, echo, restarted = b"\x01" * 16, b"\x02" * 16, b"\x03" * 16
    t0 = time.time() - 1.0
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=t0), None, driver)
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=t0 + STATE_DT_S), None, echo)
    assert "a second publisher (GID 0202" in observer.faults()[FAULT]
    assert observer.read_state().seq == 1                                  # the echo moved nothing
    # a gripper driver's few joints from its own publisher are still skipped, not a fault of their own
    observer.on_joint_state(joint_state(ts, ["panda_finger_joint1"], [0.01], stamp_s=t0 + 0.003), None, echo)
    assert observer.skipped == 1
    time.sleep(0.15)                                                       # the driver silent past stale_s
    observer.on_joint_state(joint_state(ts, PANDA, Q, stamp_s=time.time()), None, restarted)
    assert observer.read_state().seq == 2 and observer.source == restarted


def test_the_node_refuses_a_joint_state_larger_than_an_arms_before_decoding_it_and_names_its_publisher(ts):
    import types
    from tecdard.ros2 import rmw
    from tecdard.runtime.ros2_node import Ros2Node, Ros2Params
    from tecdard.runtime.ros2_subscribe import JOINT_STATE, MAX_BYTES, subscribe
    MAX_JOINT_STATE_BYTES = MAX_BYTES[JOINT_STATE]
    node = Ros2Node(Ros2Params(enabled=True), "sim", None, types=ts)
    node.node = rmw.NodeInfo(0, "z", 0, "/sim", "tecdard")
    subscribed = {}
    node.session = types.SimpleNamespace(
        declare_subscriber=lambda key, cb: subscribed.setdefault("cb", cb),
        liveliness=lambda: types.SimpleNamespace(declare_token=lambda key: None))
    got = []
    subscribe(node, "/joint_states", JOINT_STATE, lambda *args: got.append(args), "joint_states")

    class Payload(bytes):                                             # zenoh.ZBytes as the callback uses it
        def to_bytes(self):
            return bytes(self)
    decoded = []
    real_decode = node.ts.decode
    node.ts.decode = lambda raw, t: decoded.append(len(raw)) or real_decode(raw, t)
    subscribed["cb"](types.SimpleNamespace(payload=Payload(b"\0" * (MAX_JOINT_STATE_BYTES + 1)), attachment=None))
    assert got[-1][0] is None and f"{MAX_JOINT_STATE_BYTES + 1} bytes, more than an arm's" in got[-1][1]
    assert decoded == []                                              # refused undecoded
    gid = b"\x07" * 16
    raw = node.ts.encode(joint_state(ts, PANDA, Q), JOINT_STATE)
    subscribed["cb"](types.SimpleNamespace(payload=Payload(raw), attachment=Payload(rmw.attachment(1, 0, gid))))
    msg, problem, source = got[-1]
    assert problem is None and list(msg.name) == PANDA and source == gid


def test_a_drivers_wrench_is_taken_in_the_base_frame_and_a_bad_one_is_left_out_in_one_line(caplog):
    """robots/ros2_wrench.WrenchTopic: a WrenchStamped in ros2.base_frame rides with the joint states stamped near it;
    one in another frame, not finite, beyond any arm's, unstamped or from the future is left out, said in one line,
    and the wrench taken before it stays."""
    import logging
    import time
    import types
    from tecdard.robots.ros2_wrench import WrenchTopic

    def msg(force=(1.0, 2.0, 3.0), torque=(0.1, 0.2, 0.3), frame="base_link", stamp=None):
        t = time.time() if stamp is None else stamp
        V = types.SimpleNamespace
        return V(header=V(frame_id=frame, stamp=V(sec=int(t), nanosec=int((t % 1) * 1e9))),
                 wrench=V(force=V(x=force[0], y=force[1], z=force[2]), torque=V(x=torque[0], y=torque[1], z=torque[2])))
    topic = WrenchTopic("base_link", stale_s=0.1)
    assert topic.at(time.monotonic()) is None
    topic.take(msg(), None)
    force, torque = topic.at(time.monotonic())
    assert force.tolist() == [1.0, 2.0, 3.0] and torque.tolist() == [0.1, 0.2, 0.3]
    assert topic.at(time.monotonic() + 1.0) is None            # a joint state a second later: that wrench is stale
    bad = [(msg(frame="tool0"), "frame_id 'tool0'"), (msg(force=(float("nan"), 0, 0)), "not finite"),
           (msg(force=(2e4, 0, 0)), "beyond"), (msg(stamp=0.0), "stamp is zero"),
           (msg(stamp=time.time() + 10.0), "in the future")]
    for m, why in bad:
        topic.problems = 0                                      # each one said (the first of its kind)
        with caplog.at_level(logging.WARNING, logger="tecdar.ros2"):
            caplog.clear()
            topic.take(m, None)
        assert topic.problems == 1 and why in caplog.text and len(caplog.records) == 1, (why, caplog.text)
        assert "\n" not in caplog.records[0].getMessage()
    topic.take(None, "geometry_msgs/msg/WrenchStamped: 2000 bytes, more than an arm's (at most 1024)")
    assert topic.problems == 2
    assert topic.at(time.monotonic())[0].tolist() == [1.0, 2.0, 3.0]     # the good one stays
