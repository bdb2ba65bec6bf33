"""robots.ur_link against the fake UR controller, through the real ur-rtde client in its child process."""
import socket
import time

import numpy as np
import pytest

from tests.fakes.fake_ur import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, FakeController, free_loopback_host, wait_for

# the slow tier (`make check` leaves it out): the real ur-rtde client against the fake controller
pytestmark = pytest.mark.slow

pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")

from tecdard.robots.ur_link import UrLink, UrLinkError, UrLinkSettings  # noqa: E402

Q = (0.1, -1.2, 1.3, -1.6, -1.57, 0.2)
QD = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])       # rad/s
TICK_S = 0.02
CONNECT_TIMEOUT_S = 3.0
PROTECTIVE_STOPPED_BIT = 2


@pytest.fixture
def fake():
    controller = FakeController(free_loopback_host(), q=Q)
    yield controller
    controller.close()


@pytest.fixture
def link(fake):
    ur = UrLink(UrLinkSettings(fake.host, connect_timeout_s=CONNECT_TIMEOUT_S))
    ur.start()
    yield ur
    ur.stop()


def test_states_arrive_on_the_daemons_clock_and_speedj_moves_the_arm(fake, link):
    js = link.wait_state(-1, 2.0)
    np.testing.assert_allclose(js.q, Q)
    # the controller's timestamps, mapped onto this process's monotonic clock
    assert abs(js.t - time.monotonic()) < 0.1
    seqs = {js.seq}
    for _ in range(25):
        link.command_joint_velocity(QD)
        js = link.wait_state(js.seq, 1.0)
        seqs.add(js.seq)
        time.sleep(TICK_S)
    assert len(seqs) > 10                                     # a stream of states, not one
    assert js.qd[0] == pytest.approx(0.1) and js.q[0] > Q[0] + 0.02
    for _ in range(25):                                       # holding: zero rates every tick, as the daemon does
        link.hold()
        time.sleep(TICK_S)
    assert link.read_state().qd[0] == 0.0
    assert link.fault is None and link.ur_state.program_running


def test_a_stalled_daemon_is_stopped_by_the_controllers_watchdog(fake, link):
    """The control script repeats its last speedJ target forever; only the RTDE watchdog stops an
    arm whose daemon went quiet."""
    link.wait_state(-1, 2.0)
    assert fake.arm()["watchdog_hz"] == 10.0
    for _ in range(15):
        link.command_joint_velocity(QD)
        time.sleep(TICK_S)
    assert fake.arm()["qd"][0] == pytest.approx(0.1)
    time.sleep(0.3)                                           # the daemon stalls: nothing is written
    arm = fake.arm()
    assert arm["watchdog_trips"] == 1 and not arm["program_running"]
    assert wait_for(lambda: fake.arm()["qd"][0] == 0.0)
    assert wait_for(lambda: not link.ur_state.program_running)


class Admitted:
    """A state check that takes every state and keeps the controller's time of each (what the
    daemon's reader received)."""
    fault = None

    def __init__(self, link):
        self.link, self.times = link, []

    def admit(self, js) -> bool:
        self.times.append(self.link.ur_state.controller_t)
        return True


def test_while_the_daemon_rests_the_child_sends_one_state_per_rest_period(fake, link):
    """Issue 37: at rest the reader gets a state every 10 ms of the controller's clock, not every
    cycle (2 ms); a task's start gives every state again at once, and a protective stop still shows."""
    from tecdard.robots.child_link import REST_STATE_PERIOD_S
    from tecdard.robots.ur_link import CONTROLLER_CYCLE_S
    link.wait_state(-1, 2.0)
    link.gate = seen = Admitted(link)
    link.set_resting(True)
    time.sleep(0.2)
    seen.times.clear()
    time.sleep(1.0)
    rest = np.diff(seen.times)
    assert len(rest) > 20 and rest.min() >= REST_STATE_PERIOD_S - CONTROLLER_CYCLE_S / 2 - 1e-9
    fake.set(safety_status_bits=1 << PROTECTIVE_STOPPED_BIT, safety_mode=3)
    assert wait_for(lambda: link.ur_state.protective_stopped)
    link.set_resting(False)
    time.sleep(0.1)
    seen.times.clear()
    time.sleep(1.0)
    busy = np.diff(seen.times)
    assert len(busy) > len(rest) and busy.min() <= 2 * CONTROLLER_CYCLE_S + 1e-9


def test_a_controller_that_does_not_answer_is_an_error_within_the_deadline():
    host = free_loopback_host()
    listeners = [socket.create_server((host, port)) for port in (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)]
    try:                                                      # connections are accepted, nothing is ever said
        t0 = time.monotonic()
        with pytest.raises(UrLinkError, match=f"no UR controller answered at {host} within"):
            UrLink(UrLinkSettings(host, connect_timeout_s=1.0)).start()
        assert time.monotonic() - t0 < 1.0 + 3.0              # the deadline, plus ending the child
    finally:
        for s in listeners:
            s.close()


def test_no_controller_at_all_is_an_error_naming_the_host():
    host = free_loopback_host()
    with pytest.raises(UrLinkError, match=host):
        UrLink(UrLinkSettings(host, connect_timeout_s=CONNECT_TIMEOUT_S)).start()


def test_a_protective_stop_is_seen_and_explains_the_refusals_it_causes(fake, link):
    link.wait_state(-1, 2.0)
    fake.set(safety_status_bits=1 << PROTECTIVE_STOPPED_BIT, safety_mode=3)
    assert wait_for(lambda: link.ur_state.protective_stopped)
    for _ in range(10):                                       # refused: the stop's own fault says why
        link.command_joint_velocity(QD)
        time.sleep(TICK_S)
    assert link.refused is None and link.fault is None


def test_commands_refused_with_no_stop_to_explain_them_are_a_fault(fake, link):
    """The controller's runtime says its program is stopped while its status bits say it runs:
    ur-rtde refuses every speedJ, and nothing in the state explains it."""
    link.wait_state(-1, 2.0)
    fake.set(runtime_state=1)                                 # STOPPED
    deadline = time.monotonic() + 2.0
    while link.refused is None and time.monotonic() < deadline:
        link.command_joint_velocity(QD)
        time.sleep(TICK_S)
    assert link.refused == "the controller refused speedJ"
    assert link.fault is None                                 # the link itself is fine
    fake.set(runtime_state=2)                                 # PLAYING: accepted again, the fault clears
    assert wait_for(lambda: (link.command_joint_velocity(QD), link.refused)[1] is None)


def test_a_controller_that_goes_away_is_a_lost_link_not_a_dead_daemon(fake, link):
    js = link.wait_state(-1, 2.0)
    fake.close()                                              # the controller is switched off
    assert wait_for(lambda: link.exited.is_set(), 10.0)
    assert link.fault
    with pytest.raises(UrLinkError):
        link.wait_state(js.seq, 0.1)


def test_a_stopped_link_leaves_no_open_pipes(fake):
    """The UR backend makes a new link on every reconnect: the old one's pipes must be closed."""
    import os
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(3):
        ur = UrLink(UrLinkSettings(fake.host, connect_timeout_s=CONNECT_TIMEOUT_S))
        ur.start()
        ur.wait_state(-1, 2.0)
        ur.stop()
    assert len(os.listdir("/proc/self/fd")) <= before


def test_the_controllers_tcp_pose_speed_and_force_arrive_in_the_models_world(fake):
    """The controller reports in its base frame (UR's DH base, ur_description's `base`), which is a
    UR model's world: pose and speed are what our FK and Jacobian say for the same joints (to the
    fake's DH kinematics), the force arrives as the controller reports it."""
    from tecdard.robots.model import ArmModel
    model = ArmModel("ur5e")
    ur = UrLink(UrLinkSettings(fake.host, connect_timeout_s=CONNECT_TIMEOUT_S))
    ur.start()
    try:
        force_base = [1.0, 2.0, 3.0]
        fake.set(actual_TCP_force=force_base + [0.0] * 3)
        ur.wait_state(-1, 2.0)
        for _ in range(25):
            ur.command_joint_velocity(QD * 3)
            time.sleep(TICK_S)
        js = ur.read_state()
        oMtcp = model.fk(js.q)
        np.testing.assert_allclose(js.tcp_pose[:3, 3], oMtcp.translation, atol=1e-9)
        np.testing.assert_allclose(js.tcp_pose[:3, :3], oMtcp.rotation, atol=1e-9)
        # the fake's speed is its pose's derivative along qd, so to its finite step
        np.testing.assert_allclose(js.tcp_twist, model.jacobian(js.q) @ js.qd, atol=1e-6)
        assert np.linalg.norm(js.tcp_twist[:3]) > 0.05
        np.testing.assert_allclose(js.tcp_force, force_base)
        # model.measured (the daemon's proprioception) takes the controller's pose
        measured, twist = model.measured(js)
        np.testing.assert_allclose(measured.homogeneous, js.tcp_pose)
    finally:
        ur.stop()
