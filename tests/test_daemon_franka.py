"""The whole daemon on `robot.backend: franka`: the real franky client (libfranka 0.21.2) against
franky-sim's MuJoCo FR3 (tests/fakes/franka_sim.py), the fingertip board on a pseudo-terminal. Start,
state, the command watchdog, a simulator that dies and comes back, and robots that cannot work: a
version mismatch, nothing listening, a server that never answers."""
import contextlib
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from tecdard.robots.model import ArmModel
from tecdard.config import dump_yaml
from tecdard.tools.demo import distance_to_axis
from tests.conftest import ROOT, DaemonProcess, daemon_config
from tests.fakes.fake_ur import wait_for

# the slow tier (`make check` leaves it out): whole-daemon runs
# alone: franky-sim keeps its 1 kHz schedule only with the machine to itself (its tests judge nothing when it
# falls behind, and under the other workers' load it would, more often)
pytestmark = [pytest.mark.slow, pytest.mark.alone]

franky = pytest.importorskip("franky", reason="franky-control is installed by `make test` (extra `franka`)")
pytest.importorskip("franky_sim", reason="franky-sim is installed by `make test` (extra `franka-sim`)")

from tecdard.robots.franka_link import FrankaLink, FrankaLinkError, FrankaLinkSettings  # noqa: E402
from tecdard.robots.franka_server import LIBFRANKA_ROBOT_SERVER_VERSION  # noqa: E402
from tests.fakes.franka_sim import ServerProcess, free_franka_host  # noqa: E402

REFLEX_APPROACH_M = 0.08        # the reflex test's approach: still moving when the reflex is injected
Q_SIM = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785]     # franky-sim's initial posture: TCP at (0.554, 0, 0.521)
FK_TOL_M = 1e-4                 # our FK of the measured joints against franky-sim's pose at rest
CONNECT_TIMEOUT_S = 3.0
EXIT_WITHIN_S = 30.0


# The franky-sim cutter rig's fingertip, calibrated as a rig's is (docs/recordings.md): four of the
# daemon's own recordings of a 15 mm `probe` from rest against the hinge, and `tecdard
# calibrate-eta --contact <the hinge>`. The scene's fingertip springs give eta 2 and a 3 ms lag;
# the grasp's own give (the soft weld, tests/fakes/franka_sim.py GRASP_SOLREF) adds to the lag. franky-sim's
# hand holds the handle by that weld, not its fingers, so its gripper never reports a grasp: the
# grip force is the config's (estimator.grip_force_n), franky's default grasp force.
FRANKY_SIM_GRIP_N = 20.0
FRANKY_SIM_ETA_TABLE = [[FRANKY_SIM_GRIP_N, 1.971]]
FRANKY_SIM_FINGERTIP_LAG_S = 0.0065


def franka_config(host: str, port_link: str, **extra) -> dict:
    return daemon_config(**{"robot.backend": "franka", "robot.model": "fr3", "robot.name": "fr3",
                            "robot.q_home": Q_SIM,
                            "robot.franka": {"host": host, "realtime": "ignore",
                                             "connect_timeout_s": CONNECT_TIMEOUT_S},
                            "control.workspace_min": [0.2, -0.5, 0.05], "control.workspace_max": [0.8, 0.5, 0.9],
                            "imu.source": "serial", "imu.serial": {"port": port_link},
                            "estimator.eta_table": FRANKY_SIM_ETA_TABLE, "estimator.grip_force_n": FRANKY_SIM_GRIP_N,
                            "estimator.fingertip_lag_s": FRANKY_SIM_FINGERTIP_LAG_S, "sim": ..., **extra})


@pytest.fixture
def server():
    srv = ServerProcess()
    yield srv
    srv.close()


def run_refused(tmp_path, cfg: dict) -> subprocess.CompletedProcess:
    path = tmp_path / "fr3.yaml"
    path.write_text(dump_yaml(cfg))
    return subprocess.run([sys.executable, "-m", "tecdard", "run", "--config", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=EXIT_WITHIN_S)


def link_to(host: str, **kw) -> FrankaLink:
    link = FrankaLink(FrankaLinkSettings(host, realtime="ignore", connect_timeout_s=CONNECT_TIMEOUT_S, **kw))
    link.start()
    return link


def test_the_daemon_runs_on_franky_sim_and_a_simulator_that_dies_mid_task_is_a_fault_until_it_is_back(
        tmp_path, board):
    host = free_franka_host()
    srv = ServerProcess(host=host)
    # franky-sim's force is the joint torques', which carry its joints' friction (8-20 N at the TCP
    # as a motion starts): the force stop is set out of the way of this test's free motion
    # nothing in franky-sim's plain scene for the hand to hold: no gripper, or every task is not_grasped
    d = DaemonProcess(tmp_path, franka_config(host, str(board.link), **{"control.max_force_n": 100.0,
                                                                        "gripper.backend": "none"}))
    try:
        state = d.client.command("status")["state"]
        expected = ArmModel("fr3").fk(np.array(Q_SIM)).translation
        assert np.linalg.norm(np.array(state["tcp"]["p"]) - expected) < FK_TOL_M
        assert state["mode"] == "idle" and state["faults"] == []
        assert state["wrench"]["source"] == "joint_torques" and len(state["wrench"]["torque_nm"]) == 3, state["wrench"]
        reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "max_distance": 0.03})
        assert reply["ok"] is True, reply
        assert wait_for(lambda: np.linalg.norm(d.client.command("status")["state"]["tcp"]["v"]) > 1e-3, 10.0)
        srv.kill()                                     # the simulator dies mid-task, as a robot's FCI would
        # its states stop at once: stale within the budget, long before libfranka's own timeout
        # (1 s) and the link's (2 s) say that the robot has gone
        ev = d.client.wait_event(("fault",), None, 10.0)
        assert ev["code"] == "robot_stale", ev
        stop = d.client.wait_event(("protective_stop",), reply["task"], 5.0)
        assert stop["cause"] == "robot_stale"
        ended = d.client.wait_event(("task_failed", "task_done"), reply["task"], 5.0)
        assert ended["kind"] == "task_failed" and "protective stop" in ended["error"]
        ev = d.client.wait_event(("fault",), None, 10.0)
        assert ev["code"] == "robot_link" and host in ev["message"]
        refused = d.client.command("probe", {})
        assert refused["ok"] is False and refused["error"]["code"] == "fault"
        srv = ServerProcess(host=host)                 # back, at the same address
        cleared = d.client.wait_event(("fault_cleared",), None, 30.0)
        assert cleared["code"] == "robot_link"           # robot_stale cleared as the link's fault took over
        assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 5.0)
    finally:
        d.close()
        srv.close()
    log = d.log()
    assert "reconnected to " + host in log and "leaked" not in log
    assert "robot.tool_offset / robot.model" not in log        # our FK agrees with the robot's O_T_EE


def test_the_link_reads_states_at_the_robots_rate_and_the_force_from_the_torques(server):
    link = link_to(server.host)
    try:
        assert link.server_version == LIBFRANKA_ROBOT_SERVER_VERSION
        first = link.wait_state(-1, 2.0)
        time.sleep(1.0)
        n = link.read_state().seq - first.seq
        assert n > 300, n                              # about 1 kHz; a loaded CI host gets fewer
        st = link.franka_state
        assert st.force_source == "torques"            # franky-sim's O_F_ext_hat_K is zeros
        assert len(st.f_ext) == 6                      # force N, torque N m: the wrench at the TCP
        assert np.linalg.norm(st.f_ext[:3]) < 1.0      # at rest, nothing touching: gravity is taken out
        js = link.read_state()
        assert js.wrench_source == "joint_torques" and js.tcp_torque.shape == (3,)
        assert st.mode == "Idle" and st.errors == ""
        assert st.grip_width is not None and st.grip_width > 0.0 and link.identity["gripper_version"] == 3
    finally:
        link.stop()


def test_a_command_stream_that_stops_stops_the_arm_within_the_watchdog(server):
    """Each velocity command is a JointVelocityMotion held for `watchdog_s` once reached: when the
    daemon stops sending, the arm stops that long later (plus franky's ramp down), not never."""
    watchdog_s = 0.06
    link = link_to(server.host, watchdog_s=watchdog_s)
    try:
        qd = np.zeros(7)
        qd[0] = 0.2
        for _ in range(25):                            # half a second of 20 ms ticks
            link.command_joint_velocity(qd)
            time.sleep(0.02)
        moving = link.read_state()
        assert moving.qd[0] > 0.15
        last_command = time.monotonic()
        assert wait_for(lambda: abs(link.read_state().qd[0]) < 1e-3, 2.0)
        stopped_after = time.monotonic() - last_command
        assert stopped_after < watchdog_s + 0.5, stopped_after
        q_stopped = link.read_state().q[0]
        time.sleep(0.3)
        assert abs(link.read_state().q[0] - q_stopped) < 1e-4       # and it stays stopped
        # a hold is franky's stop motion: the arm rests even while commands were flowing
        for _ in range(10):
            link.command_joint_velocity(qd)
            time.sleep(0.02)
        link.hold()
        assert wait_for(lambda: abs(link.read_state().qd[0]) < 1e-3, 2.0)
        assert link.robot_fault == ""
    finally:
        link.stop()


def test_a_robot_server_of_another_version_is_an_error_naming_both_versions(tmp_path, board):
    """libfranka 0.21 checks no version when the server says success; the daemon does."""
    for extra in (("--reply-version", "9"), ("--reply-status", "incompatible", "--reply-version", "11")):
        srv = ServerProcess(*extra)
        try:
            res = run_refused(tmp_path, franka_config(srv.host, str(board.link)))
        finally:
            srv.close()
        assert res.returncode == 1
        (line,) = [x for x in res.stderr.splitlines() if x.startswith("tecdard:")]
        assert f"the robot at {srv.host} runs robot server version {extra[-1]}" in line
        assert f"speaks version {LIBFRANKA_ROBOT_SERVER_VERSION}" in line


def test_no_robot_or_a_robot_that_never_answers_is_an_error_not_a_hang(tmp_path, board):
    host = free_franka_host()
    t0 = time.monotonic()
    res = run_refused(tmp_path, franka_config(host, str(board.link)))
    assert res.returncode == 1
    (line,) = [x for x in res.stderr.splitlines() if x.startswith("tecdard:")]
    assert f"no Franka robot answered at {host}" in line
    silent = ServerProcess("--silent")
    try:
        t0 = time.monotonic()
        res = run_refused(tmp_path, franka_config(silent.host, str(board.link)))
        took = time.monotonic() - t0
    finally:
        silent.close()
    assert res.returncode == 1
    (line,) = [x for x in res.stderr.splitlines() if x.startswith("tecdard:")]
    assert f"no answer from a Franka robot at {silent.host} within {CONNECT_TIMEOUT_S:g} s" in line
    assert took < CONNECT_TIMEOUT_S + 20.0


def test_the_child_ends_a_franky_connect_that_never_returns():
    """Past the version check, franky.Robot() itself may wait for ever (an older libfranka against a
    newer server): the link's deadline ends its process."""
    silent = ServerProcess("--silent")
    try:
        link = FrankaLink(FrankaLinkSettings(silent.host, realtime="ignore", connect_timeout_s=2.0))
        link._check_version = lambda: None             # as if the version had matched
        t0 = time.monotonic()
        with pytest.raises(FrankaLinkError, match="no answer from a Franka robot"):
            link.start()
        assert time.monotonic() - t0 < 5.0
        assert not link._proc.is_alive()
    finally:
        silent.close()


def test_a_franka_config_is_checked_before_any_connection(tmp_path, board):
    cfg = franka_config("127.0.0.1", str(board.link))
    del cfg["robot"]["franka"]["host"]
    res = run_refused(tmp_path, cfg)
    assert res.returncode == 2 and "robot.franka.host: required" in res.stderr
    cfg = franka_config("127.0.0.1", str(board.link), **{"robot.model": "xarm7",
                                                          "robot.q_home": [0.0, -0.4, 0.0, 0.6, 0.0, 1.0, 0.0]})
    res = run_refused(tmp_path, cfg)
    assert res.returncode == 2 and "no Franka arm" in res.stderr
    cfg = franka_config("127.0.0.1", str(board.link))
    cfg["robot"]["franka"]["watchdog_s"] = 0.01      # shorter than two 20 ms ticks
    res = run_refused(tmp_path, cfg)
    assert res.returncode == 2 and "robot.franka.watchdog_s" in res.stderr
    cfg = franka_config("127.0.0.1", str(board.link))
    cfg["robot"]["franka"]["realtime"] = "sometimes"
    res = run_refused(tmp_path, cfg)
    assert res.returncode == 2 and "robot.franka.realtime" in res.stderr


def test_the_cutter_scene_turns_the_handle_and_the_fingertip_reports_it_over_the_wire(tmp_path):
    """The MuJoCo scene of issue 22 (tests/fakes/franka_sim.py --cutter): the FR3's hand holds the paper
    cutter's handle through a compliant fingertip whose IMU streams tecdar-imu/1 on a pty. Driven
    through the real franky client on an arc about the true hinge with the hand held level, the
    handle turns, the fingertip's gyro (parsed from the wire) reads 1/eta of the handle's rate, and
    the robot reports the handle's resistance as a force on the robot against the motion."""
    import json
    import threading

    import serial

    from tecdard.drivers.imu_wire import SamplesPacket, WireParser
    from tecdard.drivers.lsm6dsr import Scaling
    from tests.fakes.franka_sim import ETA
    pty, truth_path = str(tmp_path / "ttyF"), str(tmp_path / "truth.json")
    srv = ServerProcess("--cutter", "--pty", pty, "--truth", truth_path, "--hinge-friction", "0.3")
    link = link_to(srv.host)
    port = serial.Serial(pty, timeout=0.05)
    parser, scaling, rates, stop = WireParser(), Scaling(4000, 16), [], threading.Event()

    def read():
        while not stop.is_set():
            for pk in parser.feed(port.read(4096)):
                if isinstance(pk, SamplesPacket):
                    rates.append((time.monotonic(), scaling.to_si(pk.raw)[0].mean(axis=0)))
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        time.sleep(0.5)
        truth0 = json.load(open(truth_path))
        bias = np.mean([g for _, g in rates[-40:]], axis=0)
        hinge, axis = np.array(truth0["hinge_point"]), np.array(truth0["hinge_axis"])
        model = ArmModel("fr3")
        omega = -0.133                               # rad/s about +y: the handle's end rises
        t0 = time.monotonic()
        forces = []
        while time.monotonic() - t0 < 2.0:
            js = link.read_state()
            p = model.fk(js.q).translation
            v = np.cross(omega * axis, p - hinge)   # on the circle about the true hinge, the hand held level
            link.command_joint_velocity(model.dls_velocity(js.q, np.concatenate([v, np.zeros(3)])))
            forces.append(js.tcp_force @ (v / np.linalg.norm(v)))
            time.sleep(0.02)
        t1 = time.monotonic()
        truth_end = json.load(open(truth_path))                # the angle and the simulated time of one snapshot
        link.hold()
        time.sleep(0.3)
        truth1 = json.load(open(truth_path))
    finally:
        stop.set()
        reader.join(1.0)
        port.close()
        link.stop()
        srv.close()
    # judged in the simulation's time: franky-sim on a loaded machine runs late and drops what it cannot catch up
    # (a CI run turned 4.3 deg in the 2 s of the test's clock)
    sim_s = truth_end["sim_time_s"] - truth0["sim_time_s"]
    if sim_s < 1.0:
        pytest.skip(f"franky-sim simulated {sim_s:.2f} s of the test's 2 s: no judgement of the turn")
    commanded_deg = math.degrees(abs(omega) * sim_s)
    turned_deg = truth_end["handle_angle_deg"] - truth0["handle_angle_deg"]
    # about 15 deg in 2 s, less the start's ramp
    assert 0.5 * commanded_deg < turned_deg < 1.05 * commanded_deg + 0.5, (turned_deg, commanded_deg)
    assert truth1["base_displacement"] < 0.002               # the arc about the true hinge leaves the base
    steady = [g for t, g in rates if t0 + 0.8 < t < t1 - 0.1]
    twist = float(np.mean(steady, axis=0)[1] - bias[1])      # about the hand's y, the hinge's axis here
    assert abs(abs(twist) / abs(omega) - 1.0 / ETA) < 0.15, twist     # the fingertip passes 1/eta of the turn
    assert np.median(forces[len(forces) // 2:]) < -0.5       # the hinge's friction resists the motion


STALE_CODES = ("robot_stale", "imu_stale")


@contextlib.contextmanager
def franka_with_control(tmp_path, port_link: str):
    """(the file franky-sim takes injections from, franky-sim, a daemon on it with no gripper), closed after.
    franky-sim's force is the joint torques', which carry its joints' friction (8-20 N at the TCP as a motion
    starts): the force stop is set out of the way of free motion. Its stalls on a loaded machine
    (FRANKY_SIM_STALLS) get their state-age allowance, and so does the board's pty, fed from the test's
    process (an approach on a machine with one core busy stopped on no IMU sample for 206 ms)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    control = tmp_path / "control"
    srv = ServerProcess("--control", str(control))
    d = DaemonProcess(tmp_path, franka_config(srv.host, port_link, **{
        "control.max_force_n": 100.0, "gripper.backend": "none",
        "robot.max_state_age_s": FRANKY_SIM_STALLS["robot.max_state_age_s"],
        "control.imu_stale_s": FRANKY_SIM_STALLS["control.imu_stale_s"]}))
    try:
        yield control, srv, d
    finally:
        d.close()
        srv.close()


def reflex_run(tmp_path, board) -> tuple[list, str, str, str] | None:
    """One approach on franky-sim with a joint reflex injected mid-motion. Returns the events from the
    reflex's fault to its clearing, franky-sim's output, the task and the daemon's log; None when franky-sim (or
    the board's pty) stalled first and a stale state stopped the task before the reflex: a run that
    judged the simulator."""
    with franka_with_control(tmp_path, str(board.link)) as (control, srv, d):
        # the board's pty may start late on a loaded machine (imu_stale at start, then cleared)
        assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 10.0)
        # long enough (4 s at 20 mm/s) that the reflex lands mid-motion on a loaded machine too: a 3 cm
        # approach can end before the injection reaches franky-sim (one full run saw no reflex in 10 s)
        reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "max_distance": REFLEX_APPROACH_M})
        assert reply["ok"] is True, reply
        assert wait_for(lambda: np.linalg.norm(d.client.command("status")["state"]["tcp"]["v"]) > 1e-3, 10.0)
        control.write_text("reflex")
        ev = d.client.wait_event(("fault",), None, 10.0)
        if ev["code"] in STALE_CODES:
            print(f"franky-sim stalled before the reflex ({ev['message']}): run again")
            return None
        assert ev["code"] == "robot_reflex", ev
        # the recovery may hold franky's link long enough on a loaded machine that a stale fault is
        # raised and cleared meanwhile (CI, 2026-12-06): the reflex's own clearing is waited for
        deadline = time.monotonic() + 15.0
        cleared = d.client.wait_event(("fault_cleared",), None, 15.0)
        while cleared["code"] != "robot_reflex":
            assert cleared["code"] in STALE_CODES, cleared
            cleared = d.client.wait_event(("fault_cleared",), None, max(deadline - time.monotonic(), 0.1))
        assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 5.0)
        # the robot's clear state may reach the daemon before franky's answer to the recovery, which the
        # supervisor logs (a run of the whole file read the log between the two)
        wait_for(lambda: "recovered from robot mode" in d.log(), 5.0)
        events = list(d.client.event_log)
        return events[events.index(ev):], srv.output, reply["task"], d.log()


def test_a_reflex_is_a_fault_and_a_protective_stop_and_the_daemon_recovers_by_itself(tmp_path, board):
    """A joint reflex mid-task (injected into franky-sim's state: it simulates none) is a
    `robot_reflex` fault naming libfranka's error, a protective stop that fails the task; the
    daemon then runs franky's error recovery by itself, and the fault clears. A run in which franky-sim
    stalled first is run again (SIM_ATTEMPTS), then skipped, saying so."""
    for attempt in range(SIM_ATTEMPTS):
        run = reflex_run(tmp_path / f"run{attempt}", board)
        if run is not None:
            break
    else:
        pytest.skip(f"franky-sim stalled before the reflex in {SIM_ATTEMPTS} runs: no judgement of the daemon")
    events, output, task, log = run
    fault = events[0]
    assert "joint_reflex" in fault["message"], fault
    stop = next(e for e in events if e["kind"] == "protective_stop")
    assert stop["cause"] == "robot_reflex", stop
    ended = next(e for e in events if e["kind"] in ("task_failed", "task_done") and e.get("task") == task)
    assert ended["kind"] == "task_failed" and "protective stop" in ended["error"], ended
    assert "RECOVERED" in output               # franky's recover_from_errors reached the robot
    (line,) = [x for x in log.splitlines() if "recovered from robot mode" in x]
    assert "joint_reflex" in line


ROTATE_HINGE_TOL_M = 0.005      # issue 22: the hinge within 5 mm through the real client
REGRASP_HINGE_TOL_M = 0.010     # issue 49: after the daemon's own release and grasp on franky-sim's hand
ROTATE_ANGLE_TOL_DEG = 2.0
ARC_BASE_MAX_M = 0.002          # the arc about the estimate leaves the base (nearly) still
STRAIGHT_BASE_MIN_M = 0.020     # a straight pull drags it (as on the simulated backend, tests/test_daemon.py)
ROTATE_TIMEOUT_S = 60.0
# The end-to-end runs' allowance for the simulator itself. franky-sim shares this host's 2 cores
# with the daemon and franky's child; at times it stalls or falls 70-240 ms behind its schedule,
# and the daemon then sees a robot whose world ran late, which no real controller does. Over the
# last 38 rotates (hinge always within 1.5 mm when they finished) 3 ended on the conftest
# allowances: the divergence stop at 20-23x (against 1.0-2.5 over whole runs that kept time), or no
# IMU sample for 204-210 ms. The estimate and the motion are what these tests judge. The robot's
# states come from the same stalled process: the stale-state stop (issue 32) ended two rotates at
# 252-271 ms against the conftest's 250 ms on a loaded machine, so it gets the IMU's allowance.
FRANKY_SIM_STALLS = {"control.max_nis_ratio": 50.0, "control.imu_stale_s": 0.5, "robot.max_state_age_s": 0.5}
# Runs that kept time were at most 35 ms behind (benchmarks.franka); the failures on record came
# with stalls of 70-240 ms (CI, 2026-12-03: 126 ms behind, divergence at 60x).
SIM_LATE_S = 0.070
SIM_ATTEMPTS = 3


def cutter_run(tmp_path, *sim_args: str, config: dict | None = None, before=None, after=None,
               **fields) -> tuple[dict, dict, list, str]:
    """The daemon on franky-sim's cutter (the fingertip board's samples from MuJoCo over the pty;
    `sim_args` for tests/fakes/franka_sim.py, `config` over the daemon's): one rotate with `fields`
    (`before(d)` and `after(d)` around it). Returns its task_done or task_failed event, the scene's truth
    after it, the events and the daemon's log."""
    import json
    tmp_path.mkdir(parents=True, exist_ok=True)
    pty, truth_path = str(tmp_path / "ttyF"), str(tmp_path / "truth.json")
    srv = ServerProcess("--cutter", "--pty", pty, "--truth", truth_path, *sim_args)
    try:
        d = DaemonProcess(tmp_path, franka_config(srv.host, pty, **{**FRANKY_SIM_STALLS, **(config or {})}))
        try:
            if before is not None:
                before(d)
            task_from_s = json.load(open(truth_path))["sim_time_s"]
            reply = d.client.command("rotate", {"angle_deg": 30.0, **fields})
            stalled = not reply["ok"] and "robot_stale" in reply["error"]["message"]
            assert reply["ok"] is True or stalled, reply
            # refused while franky-sim's stall held the robot's states back: a run that judged the simulator
            ev = {"kind": "task_failed", "error": reply["error"]["message"]} if stalled else \
                d.client.wait_event(("task_done", "task_failed"), reply["task"], ROTATE_TIMEOUT_S)
            if after is not None and ev["kind"] == "task_done":
                after(d)
            time.sleep(0.2)                                   # the truth file is rewritten every 50 ms
            truth = json.load(open(truth_path))
            # how far franky-sim fell behind from the rotate's start on (the hand's own moves before it stall it
            # for up to a second, which the task never sees)
            truth["task_behind_s"] = max([b for t, b in truth["late"] if t >= task_from_s - 0.05], default=0.0)
            return ev, truth, list(d.client.event_log), d.log()
        finally:
            d.close()
    finally:
        srv.close()


def judged_run(tmp_path, judged, *sim_args: str, config: dict | None = None, before=None, after=None, **fields):
    """cutter_run, again while franky-sim fell further behind its own schedule than SIM_LATE_S during the task
    (the hand's moves before it stall the simulator for up to a second, which the task never sees) and the
    outcome is not one the test judges even then (`judged(ev, events)`; None: none is, as for a hinge's
    accuracy: a rotate on a world 250 ms late found it 32 mm off, CI's 18 mm). Such a run judged the
    simulator, not the daemon. Said each time; SIM_ATTEMPTS such runs in a row are a skip that says so."""
    for attempt in range(SIM_ATTEMPTS):
        ev, truth, events, log = cutter_run(tmp_path / f"run{attempt}", *sim_args, config=config, before=before,
                                            after=after, **fields)
        if truth["task_behind_s"] <= SIM_LATE_S or (judged is not None and judged(ev, events)):
            return ev, truth, events, log
        print(f"franky-sim fell {truth['task_behind_s'] * 1e3:.0f} ms behind in the task and the run ended "
              f"{ev['kind']} ({ev.get('error')}): run again")
    pytest.skip(f"franky-sim could not keep its schedule on this machine in {SIM_ATTEMPTS} runs (last "
                f"{truth['task_behind_s'] * 1e3:.0f} ms behind in the task): no judgement of the daemon")


def test_rotate_opens_the_cutter_on_franky_sim_about_its_true_hinge(tmp_path):
    """The paper's task through the real client: probe, localise the hinge from the fingertip's
    gyro and franky's states, follow the arc 30 deg with the gripper turning along. The hinge
    within 5 mm (measured 0.48-1.42 mm), the handle at 30 deg, the base left still. A run in which
    franky-sim fell behind its own schedule during the task is run again (judged_run)."""
    ev, truth, _, log = judged_run(tmp_path, None)
    assert ev["kind"] == "task_done", f"{ev}\n{truth}\n{log[-3000:]}"
    res = ev["result"]
    err = distance_to_axis(np.array(res["hinge"]["p"]), np.array(truth["hinge_point"]), np.array(truth["hinge_axis"]))
    summary = (f"hinge error {err * 1e3:.2f} mm, handle {truth['handle_angle_deg']:.2f} deg, "
               f"base {truth['base_displacement'] * 1e3:.2f} mm, "
               f"franky-sim behind by {truth['task_behind_s'] * 1e3:.0f} ms in the task")
    print(summary)
    assert err < ROTATE_HINGE_TOL_M, summary
    assert abs(truth["handle_angle_deg"] - 30.0) < ROTATE_ANGLE_TOL_DEG, summary
    assert abs(res["angle_deg"] - 30.0) < ROTATE_ANGLE_TOL_DEG, summary
    assert truth["base_displacement"] < ARC_BASE_MAX_M, summary


def test_a_straight_pull_on_franky_sim_drags_the_cutters_base(tmp_path):
    """The paper's failure case on the same scene: pulled straight along the first tangent with the
    gripper held, the handle's end leaves its circle by r (sqrt(1 + theta^2) - 1), 41 mm at 45 deg
    and 15 cm, and the grasp drags the base across the table. The innovations stop fitting the
    model as the hand's orientation and the handle's part ways (the divergence stop would end the
    pull first: it is set out of the way, as on the simulated backend, and so is the contact-jump
    stop, which a loaded machine's batches made fire 0.25 s into the probe once); the dragged
    base's friction may end it on the force stop, after the drag."""
    def outcome(ev, events):     # done, or stopped on the dragged base's friction
        stops = [e for e in events if e["kind"] == "protective_stop"]
        return ev["kind"] == "task_done" or (bool(stops) and stops[0]["cause"] == "force")
    ev, truth, events, log = judged_run(tmp_path, outcome, strategy="straight", angle_deg=45.0,
                                        config={"control.max_nis_ratio": 1000.0, "control.max_contact_jump_m": 1.0})
    assert outcome(ev, events), f"{ev}\n{log[-3000:]}"
    summary = f"{ev['kind']}: handle {truth['handle_angle_deg']:.1f} deg, base {truth['base_displacement'] * 1e3:.1f} mm"
    print(summary)
    assert truth["base_displacement"] > STRAIGHT_BASE_MIN_M, summary


def test_the_franka_hand_lets_go_is_refused_a_task_grasps_again_and_the_rotate_finds_the_hinge(tmp_path):
    """Issue 49, through franky's Gripper on franky-sim's hand: the hand starts holding the handle; `release`
    opens it (the weld off), a task is then refused (not_grasped); `grasp` closes it on the 25 mm handle (the
    weld on where they are); the rotate opens the cutter about its true hinge; `release` opens the hand again."""
    seen = {}

    def before(d):
        cli = d.client
        # the hand's state comes from its own reader in the link's child, a moment after the arm's
        assert wait_for(lambda: cli.command("status")["state"]["gripper"]["grasped"] is not None, 5.0)
        g = cli.command("status")["state"]["gripper"]
        assert (g["kind"], g["grasped"]) == ("franka-hand", True), g
        reply = cli.command("release", {}, timeout=20)
        assert reply["ok"] and reply["gripper"]["grasped"] is False, reply
        assert cli.command("rotate", {"angle_deg": 30.0})["error"]["code"] == "not_grasped"
        reply = cli.command("grasp", {"force": FRANKY_SIM_GRIP_N}, timeout=20)
        assert reply["ok"] and reply["gripper"]["grasped"] is True, reply
        seen["grasp"] = reply["gripper"]
        time.sleep(1.0)                     # the fingertip settles on the handle: the rotate's probe starts from rest
        # franky-sim stalling on a loaded machine may leave robot_stale for a moment (the fresh clone of 2026-12-07):
        # waited for here; a rotate it still refuses is a run that judged the simulator (cutter_run)
        wait_for(lambda: cli.command("status")["state"]["faults"] == [], 10.0)

    def after(d):
        seen["release"] = d.client.command("release", {}, timeout=20)

    ev, truth, _, log = judged_run(tmp_path, None, before=before, after=after)
    assert ev["kind"] == "task_done", f"{ev}\n{truth}\n{log[-3000:]}"
    assert abs(seen["grasp"]["width_m"] - 0.025) < 0.003 and seen["grasp"]["force_n"] == FRANKY_SIM_GRIP_N
    assert seen["release"]["ok"] and seen["release"]["gripper"]["grasped"] is False, seen["release"]
    err = distance_to_axis(np.array(ev["result"]["hinge"]["p"]), np.array(truth["hinge_point"]),
                           np.array(truth["hinge_axis"]))
    print(f"hinge error {err * 1e3:.2f} mm, franky-sim behind by {truth['task_behind_s'] * 1e3:.0f} ms in the task, "
          f"{truth['worst_behind_s'] * 1e3:.0f} ms in the run")
    # re-grasped, the pad is welded where it came to rest, without the first grasp's settling: 0.96-1.09 mm alone,
    # 6.96 mm once under the whole suite's load
    assert err < REGRASP_HINGE_TOL_M, f"hinge error {err * 1e3:.2f} mm"


def test_recover_runs_frankys_recovery_and_says_a_reflex_without_an_error_is_a_persons(tmp_path, board):
    """Issue 52: `recover` on a Franka. A robot held in Reflex with no error (a known libfranka case, injected into
    franky-sim's state) is a robot_reflex fault; franky's error recovery does not clear it, and `recover` says so
    and what a person must do. Once the user stop has been pressed and released the fault clears, `recover` has
    nothing left to do, and a task runs."""
    with franka_with_control(tmp_path, str(board.link)) as (control, srv, d):
        assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 10.0)
        control.write_text("reflex-stuck")
        assert wait_for(lambda: any(f["code"] == "robot_reflex"
                                    for f in d.client.command("status")["state"]["faults"]), 10.0)
        fault = next(f for f in d.client.command("status")["state"]["faults"] if f["code"] == "robot_reflex")
        assert fault["message"].endswith("(`recover` clears it)") and "Reflex" in fault["message"], fault
        reply = d.client.command("recover", {}, timeout=30.0)
        assert reply["ok"] is False and reply["error"]["code"] == "not_recovered", reply
        assert "stays in Reflex without an error" in reply["error"]["message"]
        assert "user stop" in reply["error"]["message"]
        refused = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "max_distance": 0.01})
        assert refused["ok"] is False and refused["error"]["code"] == "fault", refused
        control.write_text("user-stop")
        assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 10.0), \
            d.client.command("status")["state"]["faults"]
        again = d.client.command("recover", {}, timeout=30.0)
        assert again == {"ok": True, "steps": ["the robot reports no fault: nothing to recover"],
                         "took_s": again.get("took_s")}, again
        reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "max_distance": 0.01})
        assert reply["ok"] is True, reply
        ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 30.0)
        # the arm moved the whole way down free air: the task ran to its own end (no contact there)
        assert ev["kind"] == "task_done" or "no contact within max_distance" in ev.get("error", ""), ev
