"""The gripper (robots/gripper.py): the Robotiq client against a protocol fake written from Robotiq's manual
(tests/fakes/robotiq_urcap.py), the commands' validation, and on the simulated arm `grasp`, a refused task while
the hand is empty, `release`, and where the grip force goes (the estimator, the recording, the MCAP)."""
import threading
import time

import numpy as np
import pytest

from tecdard.api import commands as C
from tecdard.robots.gripper import (ASSUMED, COMMANDED, GripperError, GripperParams, ManualGripper, RobotiqGripper,
                                    force_source, gripper_kind)
from tests.conftest import rotate_on_the_cutter
from tests.fakes.robotiq_urcap import FakeUrcap, free_urcap_host

HINGE_TOL_M = 0.010


@pytest.fixture
def urcap():
    fake = FakeUrcap(free_urcap_host())
    yield fake
    fake.close()


@pytest.mark.slow
def test_robotiq_activates_grasps_an_object_finds_an_empty_hand_and_releases(urcap):
    g = RobotiqGripper(urcap.host, model="2f-85")
    assert "SET ACT 1" in urcap.commands and urcap.reg["STA"] == 3       # activated at connect
    st = g.grasp(60.0, 0.0, 0.05, 5.0)
    assert st.grasped is True and st.force_source == COMMANDED
    assert st.width_m == pytest.approx(0.025, abs=0.001)                # the fake's 25 mm object
    assert st.force_n == pytest.approx(60.0, abs=(235 - 20) / 255)       # FOR is a byte over 20..235 N
    assert any(c.startswith("SET POS 255 SPE") for c in urcap.commands)
    st = g.release(0.08, 0.1, 5.0)
    assert st.grasped is False and st.force_n is None and st.width_m == pytest.approx(0.085, abs=1e-3)
    urcap.set_object(None)
    st = g.grasp(60.0, 0.0, 0.15, 5.0)
    assert st.grasped is False and st.width_m == pytest.approx(0.0, abs=1e-3) and st.force_n is None
    g.close()


def test_robotiq_failures_are_one_line_each(urcap):
    with pytest.raises(GripperError, match="no Robotiq URCap answered at 127.0.0.1:1"):
        RobotiqGripper("127.0.0.1", port=1)
    g = RobotiqGripper(urcap.host)
    with pytest.raises(GripperError, match="had not stopped after 0.05 s"):
        g.grasp(60.0, 0.0, 0.02, 0.05)                                   # 85 mm at 20 mm/s
    g.release(0.08, 0.15, 5.0)
    # the daemon's stop ends a close under way: GTO 0, and the grasp says so
    out = {}

    def close_slowly():
        try:
            g.grasp(60.0, 0.0, 0.02, 5.0)
        except GripperError as exc:
            out["error"] = str(exc)
    th = threading.Thread(target=close_slowly)
    th.start()
    time.sleep(0.3)
    g.stop()
    th.join(5.0)
    assert "SET GTO 0" in urcap.commands and not th.is_alive()
    assert out["error"] == "Robotiq: stopped by the daemon's stop"
    assert urcap.reg["OBJ"] != 2                                          # stopped before it met the object
    urcap.close()                                                         # the controller goes away
    st = g.state()
    assert st.fault and "Robotiq URCap" in st.fault
    g.close()


def test_a_urcap_that_answers_nonsense_is_refused_not_believed(urcap):
    g = RobotiqGripper(urcap.host)
    g._ask = lambda line: "ack" if line.startswith("SET") else "POS banana"   # not the register asked for
    with pytest.raises(GripperError, match="answered 'POS banana' to GET PRE"):
        g.grasp(60.0, 0.0, 0.05, 1.0)
    g.close()


def test_the_fake_answers_as_the_manual_says(urcap):
    import socket
    with socket.create_connection((urcap.host, 63352), timeout=2) as s:
        f = s.makefile("rw")
        for line, want in (("GET STA", "STA 0"), ("SET GTO 1", "ack"), ("GET FLT", "FLT 5"), ("SET ACT 1", "ack"),
                           ("SET POS 300", "?"), ("HELLO", "?"), ("GET XYZ", "?")):
            f.write(line + "\n")
            f.flush()
            assert f.readline().strip() == want, line


def test_grasp_and_release_payloads_are_checked():
    limits = C.Limits()
    assert C.validate("grasp", {"force": 40, "width": 0.02}, limits) == {"force_n": 40.0, "width_m": 0.02,
                                                                           "speed_m_s": None}
    assert C.validate("release", {}, limits) == {"width_m": None, "speed_m_s": None}
    for verb, obj, code in (("grasp", {"force": -1}, C.OUT_OF_LIMITS), ("grasp", {"force": "hard"}, C.BAD_TYPE),
                            ("grasp", {"grip": 3}, C.UNKNOWN_FIELD), ("release", {"force": 3}, C.UNKNOWN_FIELD),
                            ("release", {"width": 2.0}, C.OUT_OF_LIMITS)):
        with pytest.raises(C.CommandError) as exc:
            C.validate(verb, obj, limits)
        assert exc.value.code == code, (verb, obj, exc.value)


def test_which_gripper_and_where_its_force_comes_from():
    assert gripper_kind("auto", "sim") == "sim" and gripper_kind("auto", "franka") == "franka-hand"
    assert gripper_kind("auto", "ur") == "none" and gripper_kind("auto", "ros2") == "none"
    with pytest.raises(GripperError, match="franka-hand needs robot.backend: franka, not ur"):
        gripper_kind("franka-hand", "ur")
    assert force_source("manual") == ASSUMED and force_source("none") == ASSUMED
    assert force_source("robotiq") == COMMANDED
    m = ManualGripper(30.0)
    assert m.state().force_n == 30.0 and m.state().grasped is None and not m.reports_grasp
    assert m.grasp(22.0, 0.0, 0.02, 1.0).force_n == 22.0 and m.release(0.08, 0.02, 1.0).force_n is None


def test_a_config_that_asks_more_than_its_own_limit_is_refused():
    from tecdard.config import Config, ConfigError
    with pytest.raises(ConfigError, match="force_n: 150 N is above max_force_n 140 N"):
        GripperParams.from_config(Config({"gripper": {"force_n": 150}}).section("gripper"))


@pytest.mark.slow
def test_on_the_simulated_arm_release_empties_the_hand_tasks_refuse_and_a_grasp_sets_the_force(make_daemon,
                                                                                                tmp_path):
    d = make_daemon(**{"record.enabled": True, "record.dir": str(tmp_path / "rec")})
    cli = d.client
    g = cli.command("status")["state"]["gripper"]
    assert (g["kind"], g["grasped"], g["force_source"]) == ("sim", True, "commanded")
    reply = cli.command("release", {}, timeout=10)
    assert reply["ok"] and reply["gripper"]["grasped"] is False
    refused = cli.command("rotate", {"angle_deg": 10})
    assert refused["error"]["code"] == "not_grasped" and "grasp the object first" in refused["error"]["message"]
    assert cli.command("grasp", {"force": 400}, timeout=10)["error"]["code"] == "out_of_limits"
    assert cli.command("grasp", {"force": 200}, timeout=10)["error"]["code"] == "out_of_limits"   # max_force_n
    reply = cli.command("grasp", {"force": 25}, timeout=10)
    assert reply["ok"] and reply["gripper"]["force_n"] == 25.0, reply
    assert rotate_on_the_cutter(d, 20.0) < HINGE_TOL_M
    # the recording of that rotate: the grip force the grasp set, where it came from, the hand's state
    from tecdard.recording.format import load_recording
    from tecdard.recording.live import load_live
    path = cli.wait_event(("recording_written",), None, 30.0)["path"]
    rec, live = load_recording(path), None
    live = load_live(path, rec)
    # the capture's pre-roll reaches back before the grasp: the hand empty then (the estimator took the
    # configured 30 N), holding at 25 N from the grasp on
    held = live.gripper[:, 1] == 1.0
    since = np.flatnonzero(~held)[-1] + 1                   # the grasp
    assert rec.meta["grip_force_source"] == "commanded" and len(held) - since > 0.5 * len(held)
    assert np.all(rec.grip_force[since:] == 25.0) and np.all(rec.grip_force[~held] == 30.0)
    assert np.allclose(live.gripper[since:, 0], 0.025) and np.all(live.gripper[~held] == [0.08, 0.0])
    # and in its MCAP: /gripper at every proprioception sample, the force only while it holds
    import json
    from tests.conftest import tecdard
    from tests.test_recorder import read_mcap
    out = tmp_path / "rotate.mcap"
    assert tecdard("export", path, "--mcap", str(out)).returncode == 0
    msgs = [json.loads(d) for _, _, d in read_mcap(out)["/gripper"]]
    assert len(msgs) == len(rec.tcp_t)
    assert msgs[-1] == {"width_m": 0.025, "force_n": 25.0, "grasped": True}
    assert {"width_m": 0.08, "force_n": None, "grasped": False} in msgs
    # and the arm's own wrench (the simulator's contact force) on /wrench, as the recording has it
    wrench = [json.loads(d) for _, _, d in read_mcap(out)["/wrench"]]
    assert len(wrench) == len(rec.tcp_t) == len(live.wrench)
    assert wrench[-1]["source"] == "sim_contact" and wrench[-1]["torque_nm"] is None
    assert [wrench[-1]["force_n"][a] for a in "xyz"] == live.wrench[-1, :3].tolist()
    # `tecdard plot` draws that force under the TCP: one panel more than the same recording without it
    import struct
    bare = tmp_path / "bare.npz"
    with np.load(path) as z:
        np.savez(bare, **{k: z[k] for k in z.files if k != "tcp_wrench"})
    heights = []
    for src, png in ((path, tmp_path / "with.png"), (bare, tmp_path / "bare.png")):
        assert tecdard("plot", src, "-o", str(png)).returncode == 0
        heights.append(struct.unpack(">II", png.read_bytes()[16:24])[1])       # the PNG's IHDR: width, height
    assert heights[0] > heights[1], heights


def test_doctor_says_whether_the_urcap_answers_and_the_gripper_is_activated(urcap):
    from tecdard.config import Config
    from tecdard.robots.gripper import check_gripper
    robot = Config({"robot": {"ur": {"host": urcap.host}}}).section("robot")
    params = GripperParams()
    warn = check_gripper(params, "robotiq", robot)
    assert warn.status == "warn" and "not activated" in warn.detail
    urcap.reg.update(ACT=1, STA=3)
    assert check_gripper(params, "robotiq", robot).status == "pass"
    urcap.close()
    fail = check_gripper(params, "robotiq", robot)
    assert fail.status == "fail" and f"no Robotiq URCap answers at {urcap.host}:63352" in fail.detail
    assert "URCap" in fail.fix
    assert check_gripper(params, "none", robot).status == "pass"
