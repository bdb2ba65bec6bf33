"""The fake UR controller's RTDE server against the real ur-rtde client (issue 19's ground).

The client is PyPI's ur-rtde (C++ behind pybind11), never mocked: what these tests check is that
the fake speaks RTDE v2 as the client expects it. The fake runs as a process of its own, as a
controller does: the binding holds the GIL while it blocks in a handshake.
"""
import time

import pytest

from tests.fakes.fake_ur import FakeController, UrKinematics, free_loopback_host, wait_for

rtde_receive = pytest.importorskip("rtde_receive", reason="ur-rtde is installed by `make test` (extra `ur`)")
rtde_io = pytest.importorskip("rtde_io")
dashboard_client = pytest.importorskip("dashboard_client")

Q = (0.1, -1.2, 1.3, -1.6, -1.57, 0.2)
TCP_OFFSET = (0.0, 0.0, 0.15, 0.0, 0.0, 0.0)      # the controller's TCP setting: 15 cm out of the flange
UR_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force",
                "robot_mode", "safety_mode", "robot_status_bits", "safety_status_bits", "runtime_state"]
CONTROLLER_PERIOD_S = 0.002                        # an e-Series controller's cycle (500 Hz)
PROTECTIVE_STOPPED_BIT = 2                         # safety_status_bits: bit 0 normal mode, bit 2 protective stop
SETTLE_S = 0.3                                     # for the client's receive thread to take new packages


@pytest.fixture
def fake():
    controller = FakeController(free_loopback_host(), q=Q, tcp_offset=TCP_OFFSET)
    yield controller
    controller.close()


@pytest.mark.slow
def test_the_real_receive_client_reads_the_controller_state_and_its_stops(fake):
    r = rtde_receive.RTDEReceiveInterface(fake.host, 500.0, UR_VARIABLES)
    try:
        assert wait_for(lambda: r.getActualQ() == list(Q))
        assert r.getActualTCPPose() == pytest.approx(UrKinematics("UR5e", TCP_OFFSET).pose(Q), abs=1e-12)
        assert r.getRobotMode() == 7 and r.getSafetyMode() == 1 and not r.isProtectiveStopped()
        # the controller's clock counts its cycles: a timestamp is a whole number of them
        t = r.getTimestamp()
        assert t > 0 and abs(t / CONTROLLER_PERIOD_S - round(t / CONTROLLER_PERIOD_S)) < 1e-6
        assert wait_for(lambda: r.getTimestamp() > t)
        fake.set(safety_status_bits=1 << PROTECTIVE_STOPPED_BIT, safety_mode=3)
        assert wait_for(r.isProtectiveStopped) and r.getSafetyMode() == 3
    finally:
        r.disconnect()


@pytest.mark.slow
def test_the_clients_default_recipe_is_served_whole(fake):
    """Without a variable list the client asks for everything its PolyScope version has."""
    r = rtde_receive.RTDEReceiveInterface(fake.host)
    try:
        assert wait_for(lambda: r.getActualQ() == list(Q))
        assert r.getSpeedScaling() == 1.0
    finally:
        r.disconnect()


def test_an_unknown_variable_is_refused_as_the_controller_refuses_it(fake):
    with pytest.raises(RuntimeError, match="not found by the controller"):
        rtde_receive.RTDEReceiveInterface(fake.host, 500.0, ["timestamp", "no_such_variable"])


def test_what_the_client_writes_reaches_the_controller(fake):
    io = rtde_io.RTDEIOInterface(fake.host)
    try:
        assert io.setInputIntRegister(18, 5) and io.setInputDoubleRegister(19, 2.5)
        assert wait_for(lambda: fake.inputs()[1] >= 2)
        inputs, _ = fake.inputs()
        assert inputs["input_int_register_18"] == 5 and inputs["input_double_register_19"] == 2.5
    finally:
        io.disconnect()         # before the fake goes: the client aborts its process on a lost connection


def test_the_real_dashboard_client_talks_to_the_dashboard_server(fake):
    db = dashboard_client.DashboardClient(fake.host)
    db.connect()                         # reads the server's greeting
    try:
        assert db.isConnected() and db.isInRemoteControl()
        assert db.polyscopeVersion() == "5.11.0.0"
        assert db.robotmode() == "Robotmode: RUNNING" and db.safetystatus() == "Safetystatus: NORMAL"
        assert db.programState().startswith("STOPPED") and not db.running()
        assert db.getRobotModel() == "UR5"
    finally:
        db.disconnect()
    sent, not_understood = fake.dashboard_commands()
    assert {"is in remote control", "PolyscopeVersion", "robotmode", "safetystatus", "programState", "running",
            "get robot model"} <= set(sent)
    assert not_understood == []


@pytest.mark.slow
def test_a_protective_stop_is_unlocked_on_the_dashboard_5_s_after_it_and_clears_on_rtde(fake):
    """UR's rule: the dashboard refuses to unlock a protective stop until 5 s after it (ur-rtde raises on the
    answer), and the pendant's safety popup stays until it is closed."""
    import time
    from tests.fakes.fake_ur import UNLOCK_AFTER_S
    r = rtde_receive.RTDEReceiveInterface(fake.host, 500.0, UR_VARIABLES)
    db = dashboard_client.DashboardClient(fake.host)
    db.connect()
    try:
        fake.set(safety_status_bits=1 << PROTECTIVE_STOPPED_BIT, safety_mode=3)
        t_stop = time.monotonic()
        assert wait_for(r.isProtectiveStopped)
        assert db.safetystatus() == "Safetystatus: PROTECTIVE_STOP" and fake.arm()["popup"] is True
        with pytest.raises(Exception, match="5s after occurrence"):
            db.unlockProtectiveStop()
        time.sleep(max(0.0, t_stop + UNLOCK_AFTER_S + 0.1 - time.monotonic()))
        db.unlockProtectiveStop()
        db.closeSafetyPopup()
        assert fake.arm()["popup"] is False
        assert wait_for(lambda: not r.isProtectiveStopped()) and r.getSafetyMode() == 1
        assert db.safetystatus() == "Safetystatus: NORMAL"
    finally:
        db.disconnect()
        r.disconnect()


rtde_control = pytest.importorskip("rtde_control")
SPEEDJ_QD = [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]     # rad/s, joint 1 (the base) only
SPEEDJ_ACCEL = 1.0                             # rad/s^2
TICK_S = 0.02


@pytest.mark.slow
def test_the_real_control_client_runs_its_script_and_speedj_moves_the_arm(fake):
    c = rtde_control.RTDEControlInterface(fake.host)
    try:
        assert c.isProgramRunning()                          # the script went in on 30003 and runs
        q0 = fake.arm()["q"][0]
        for _ in range(25):                                  # 0.5 s of 20 ms ticks
            assert c.speedJ(SPEEDJ_QD, SPEEDJ_ACCEL, TICK_S)
            time.sleep(TICK_S)
        arm = fake.arm()
        assert arm["qd"][0] == pytest.approx(0.1) and arm["q"][0] - q0 > 0.02
        assert all(v == 0.0 for v in arm["qd"][1:])
        assert c.speedStop(2.0)
        assert wait_for(lambda: fake.arm()["qd"][0] == 0.0)
        commands = fake.arm()["commands"]
        assert commands.count(9) >= 25 and commands[-1] == 15      # speedJ each tick, then speedStop
    finally:
        c.stopScript()
        c.disconnect()
    assert not fake.arm()["program_running"]


@pytest.mark.slow
def test_a_protective_stop_halts_the_arm_and_the_controller_refuses_speedj(fake):
    c = rtde_control.RTDEControlInterface(fake.host)
    try:
        for _ in range(10):
            c.speedJ(SPEEDJ_QD, SPEEDJ_ACCEL, TICK_S)
            time.sleep(TICK_S)
        fake.set(safety_status_bits=1 << PROTECTIVE_STOPPED_BIT, safety_mode=3)
        assert wait_for(lambda: not c.isProgramRunning())               # PolyScope pauses the program
        assert c.speedJ(SPEEDJ_QD, SPEEDJ_ACCEL, TICK_S) is False      # refused: the program is paused
        assert fake.arm()["qd"] == [0.0] * 6
    finally:
        c.disconnect()


@pytest.mark.slow
def test_the_controllers_watchdog_stops_a_client_that_went_quiet(fake):
    c = rtde_control.RTDEControlInterface(fake.host)
    try:
        assert c.setWatchdog(10.0) and fake.arm()["watchdog_hz"] == 10.0
        for _ in range(15):                                  # fed every 20 ms: no trip
            assert c.speedJ(SPEEDJ_QD, SPEEDJ_ACCEL, TICK_S)
            time.sleep(TICK_S)
        assert fake.arm()["watchdog_trips"] == 0
        time.sleep(0.3)                                      # over 1 / 10 Hz without a write
        arm = fake.arm()
        assert arm["watchdog_trips"] == 1 and not arm["program_running"]
        assert wait_for(lambda: fake.arm()["qd"][0] == 0.0)
    finally:
        c.disconnect()
