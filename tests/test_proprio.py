"""Proprioception: every joint state the robot reports reaches the estimator, as TCP pose and twist,
on the link's own reader (feed_states) or on a thread of its own (proprio_loop)."""
import threading

import numpy as np

from tecdard.robots.backend import JointState
from tecdard.robots.model import ArmModel
from tecdard.runtime.messages import DropOldestRing
from tecdard.runtime.workers import PROPRIO_RING, ProprioFeed, proprio_loop

Q_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
JOIN_S = 2.0


class ScriptedArm:
    """A robot that has reported `states` (seq 1, 2, ...): wait_state hands over the next one after
    `seq`, fails `failures` times first, and after the last one waits out its timeout."""

    def __init__(self, states, failures=0):
        self.states = states
        self.failures = failures
        self.done = threading.Event()

    def wait_state(self, seq, timeout):
        if self.failures:
            self.failures -= 1
            raise RuntimeError("the link is down")
        later = [js for js in self.states if js.seq > seq]
        if later:
            return later[0]
        self.done.set()
        threading.Event().wait(timeout)
        return self.states[-1]


def states(n, twist=None):
    rng = np.random.default_rng(4)
    return [JointState(t=0.01 * k, q=Q_HOME + rng.normal(0, 0.05, 7), qd=rng.normal(0, 0.1, 7), seq=k + 1,
                       tcp_twist=twist) for k in range(n)]


def run(arm, ring):
    stop = threading.Event()
    th = threading.Thread(target=proprio_loop, args=(arm, ProprioFeed(ArmModel("panda"), ring), stop), daemon=True)
    th.start()
    assert arm.done.wait(JOIN_S * 5)
    stop.set()
    th.join(JOIN_S)
    assert not th.is_alive()           # the stop event ends it
    return ring.drain()


def test_every_state_arrives_once_in_order_as_tcp_pose_and_twist():
    reported = states(20)
    got = run(ScriptedArm(reported, failures=2), DropOldestRing(PROPRIO_RING))   # a failing link is waited out
    model = ArmModel("panda")
    assert [m.t for m in got] == [js.t for js in reported]
    for s, js in zip(got, reported):
        assert np.isnan(s.grip_force_n)                     # not measured: the configured constant applies
        oMtcp, twist = model.fk_twist(js.q, js.qd)
        np.testing.assert_allclose(s.p_world, oMtcp.translation, atol=1e-12)
        np.testing.assert_allclose(s.R_world_tcp, oMtcp.rotation, atol=1e-12)
        np.testing.assert_allclose(np.r_[s.v_world, s.w_world], twist, atol=1e-12)
        np.testing.assert_array_equal(s.q, js.q)              # the joints ride along for the recorder


def test_a_reported_tcp_twist_is_used_and_a_full_ring_overwrites_the_oldest_without_blocking():
    twist = np.array([0.01, 0.0, -0.02, 0.0, 0.1, 0.0])
    ring = DropOldestRing(4)
    got = run(ScriptedArm(states(10, twist)), ring)
    assert len(got) == 4 and ring.overwritten == 6          # the newest kept; the loop went on
    assert [m.t for m in got] == [0.06, 0.07, 0.08, 0.09]
    for m in got:
        np.testing.assert_array_equal(np.r_[m.v_world, m.w_world], twist)


def test_a_malformed_state_is_skipped_and_the_rest_still_arrive():
    reported = states(5)
    reported[2] = JointState(t=0.02, q=np.zeros(3), qd=np.zeros(3), seq=3)     # wrong shape: FK raises
    got = run(ScriptedArm(reported), DropOldestRing(PROPRIO_RING))
    assert [m.t for m in got] == [0.0, 0.01, 0.03, 0.04]


def test_a_reported_tcp_pose_and_grip_force_are_what_reaches_the_estimator():
    """A robot's own calibrated TCP pose (a UR controller's) wins over our FK; its gripper's force
    (where it reads one) goes with the sample, for eta's schedule."""
    reported = states(3)
    pose = np.eye(4)
    pose[:3, 3] = [0.4, -0.1, 0.3]
    for k, js in enumerate(reported):
        js.tcp_pose, js.grip_force = pose, 20.0 + k
    got = run(ScriptedArm(reported), DropOldestRing(PROPRIO_RING))
    assert [m.grip_force_n for m in got] == [20.0, 21.0, 22.0]
    for m in got:
        np.testing.assert_array_equal(m.p_world, pose[:3, 3])
        np.testing.assert_array_equal(m.R_world_tcp, np.eye(3))


def test_a_link_hands_every_state_it_admits_to_the_feed_on_its_own_reader():
    """Issue 37: a link backend's reader feeds the estimator itself (no proprioception thread to
    wake per state); a state its check refuses never reaches the feed; a repeated seq is taken once."""
    import types
    from tecdard.robots.child_link import ChildLink
    ring = DropOldestRing(PROPRIO_RING)
    feed = ProprioFeed(ArmModel("panda"), ring)
    link = ChildLink(types.SimpleNamespace(), 1.0)
    link.gate = types.SimpleNamespace(admit=lambda js: js.seq != 3, fault=None)
    link.on_state = feed
    reported = states(5)
    for js in reported + [reported[-1]]:
        link._publish(js)
    got = ring.drain()
    assert [m.t for m in got] == [0.0, 0.01, 0.03, 0.04]
    assert link.read_state() is reported[-1]
