"""`recover` on the simulated arm (issue 52): the simulated controller's protective stop, raised the way a real
arm's is (a force at the TCP beyond its limit, sim.robot.protective_stop_force_n), held until `recover`, which
unlocks it; then a task runs. The UR's and the Franka's are tested against their protocol fakes
(tests/test_daemon_ur.py, tests/test_ur_rotate.py, tests/test_daemon_franka.py)."""
import numpy as np
import pytest

from benchmarks.onset_live import scene
from tests.fakes.fake_ur import wait_for

TASK_TIMEOUT_S = 60.0


@pytest.mark.slow
def test_a_protective_stop_on_the_simulated_arm_holds_until_recover_then_a_task_runs(make_daemon):
    # a block held nearly level onto a table: the grasp's force passes 1 N some 100 ms after the touch at 20 mm/s
    d = make_daemon(**{"sim.robot.protective_stop_force_n": 1.0, **scene("table")})
    cli = d.client
    reply = cli.command("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                     "stop_angle_deg": 5.0})
    assert reply["ok"] is True, reply
    stop = cli.wait_event(("protective_stop",), reply["task"], TASK_TIMEOUT_S)
    assert stop["cause"] == "robot_protective_stop", stop
    failed = cli.wait_event(("task_failed",), reply["task"], 10.0)
    assert "protective stop" in failed["error"], failed
    faults = cli.command("status")["state"]["faults"]
    (fault,) = [f for f in faults if f["code"] == "robot_protective_stop"]
    assert "sim.robot.protective_stop_force_n 1 N" in fault["message"]
    assert fault["message"].endswith("(`recover` clears it)"), fault
    # held: the arm does not move, and tasks are refused, until recover
    p0 = np.array(cli.command("status")["state"]["tcp"]["p"])
    refused = cli.command("home", {})
    assert refused["ok"] is False and refused["error"]["code"] == "fault", refused
    assert np.linalg.norm(np.array(cli.command("status")["state"]["tcp"]["p"]) - p0) < 1e-3
    # the block still presses on the table: the stop holds (a real controller's recurs at once), and recover says
    # what a person must do
    held = cli.command("recover", {}, timeout=30.0)
    assert held["ok"] is False and held["error"]["code"] == "not_recovered", held
    assert "the protective stop holds" in held["error"]["message"] and "lets go of the object" in held["error"]["message"]
    # letting go of the object (the one grip command a protective stop allows) frees the tool; recover then unlocks
    released = cli.command("release", {}, timeout=10.0)
    assert released["ok"] is True and released["gripper"]["grasped"] is False, released
    assert cli.command("grasp", {}, timeout=10.0)["error"]["code"] == "fault"
    reply = cli.command("recover", {}, timeout=30.0)
    assert reply == {"ok": True, "steps": ["unlocked the simulated controller's protective stop"],
                     "took_s": reply.get("took_s")}, reply
    assert wait_for(lambda: cli.command("status")["state"]["faults"] == [], 5.0)
    events = [e["kind"] for e in cli.event_log]
    assert "recover_started" in events and "recover_failed" in events and "recovered" in events
    # and a task runs: home, with a fresh world (a block held again)
    reply = cli.command("home", {"reset_world": True})
    assert reply["ok"] is True, reply
    ev = cli.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", ev


@pytest.mark.slow
def test_recover_with_nothing_to_recover_says_so_and_is_refused_during_a_task(make_daemon):
    d = make_daemon()
    cli = d.client
    assert cli.command("recover", {}, timeout=30.0)["steps"] == ["the arm reports no fault: nothing to recover"]
    reply = cli.command("rotate", {"angle_deg": 10.0})
    assert reply["ok"] is True, reply
    busy = cli.command("recover", {}, timeout=30.0)
    assert busy["ok"] is False and busy["error"]["code"] == "busy" and "rotate" in busy["error"]["message"], busy
    assert cli.command("recover", {"force": 1})["error"]["code"] == "unknown_field"
    cli.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
