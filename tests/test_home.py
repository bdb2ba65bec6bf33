"""`home` (issue 33): a slow joint move to q_home on every backend, within the joint speed asked and the
TCP speed limit, refused in fault or where its path leaves the workspace; `--reset-world` on the
simulated robot lets go of the object and builds a fresh world, so that a rotate works again."""
import math
import time

import numpy as np
import pytest

from tecdard.control.home import HomeRefused, plan_home
from tecdard.runtime.messages import StartTask
from tests.test_controller_lies import Feed, Ring, control_on, events

TICK_S = 0.02
OFFSET_RAD = np.array([0.3, -0.2, 0.25, 0.2, -0.15, 0.1, 0.2])   # where the arm starts, from q_home


def run_home(feed: Feed, fields: dict, q_start: np.ndarray, seconds: float = 40.0):
    """The control thread on the backend's link, the controller integrating what it is told (2 ms
    states): the control thread, the joints it was at each tick, and the reply."""
    ct = control_on(feed)
    t0 = time.monotonic()
    q = q_start.copy()
    feed.send(t0, q)
    ct.tick(t0)
    ct.submit(StartTask(1, "home", dict(fields)))
    qs = []
    for k in range(1, int(seconds / TICK_S)):
        now = t0 + k * TICK_S
        qd = feed.commands[-1][1] if feed.commands and feed.commands[-1][0] == "qd" else np.zeros(len(q))
        for i in range(10):
            t = now - TICK_S + (i + 1) * 0.002
            q = q + qd * 0.002
            feed.send(t, q, qd)
        Ring.last_t = now
        ct.tick(now)
        qs.append(q.copy())
        if k > 5 and ct.runner.task is None:
            break
    reply = ct.replies.get_nowait().payload
    return ct, np.array(qs), reply


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["ur", "franka", "sim"])
def test_home_moves_every_backend_to_q_home_within_its_speeds(backend):
    if backend == "ur":
        pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    feed = Feed(backend)
    n = len(feed.q0)
    start = feed.q0 + OFFSET_RAD[:n]
    speed_deg_s = 8.0
    ct, qs, reply = run_home(feed, {"joint_speed_deg_s": speed_deg_s, "reset_world": False}, start)
    assert reply["ok"], reply
    done = events(ct, "task_done", "task_failed")
    assert done and done[-1]["kind"] == "task_done", done
    assert np.max(np.abs(qs[-1] - feed.q0)) < math.radians(0.2)
    rates = np.array([c[1] for c in feed.commands if c[0] == "qd"])
    assert np.max(np.abs(rates)) <= 1.2 * math.radians(speed_deg_s) + 1e-9      # the plan's, plus bounded feedback
    tcp = np.array([feed.model.fk(q).translation for q in qs])
    tcp_speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / TICK_S
    assert np.max(tcp_speed) <= 1.1 * ct.params.max_speed, np.max(tcp_speed)        # limits.max_speed, 0.05 m/s


def test_home_is_refused_in_fault_and_where_its_path_leaves_the_workspace():
    feed = Feed("sim")
    ct = control_on(feed)
    t = time.monotonic()
    feed.send(t, feed.q0 + OFFSET_RAD)
    feed.send(t + 0.002, np.r_[feed.q0[:1], 7.0, feed.q0[2:]] + OFFSET_RAD)     # a lie: a fault holds
    Ring.last_t = t + 0.02
    ct.tick(t + 0.02)
    assert "robot_state" in ct.faults
    ct.submit(StartTask(1, "home", {"joint_speed_deg_s": 10.0, "reset_world": False}))
    ct.tick(t + 0.04)
    reply = ct.replies.get_nowait().payload
    assert reply["error"]["code"] == "fault" and "robot_state" in reply["error"]["message"]
    assert not any(c[0] == "qd" and np.any(c[1]) for c in feed.commands)

    model = feed.model
    fk = lambda q: model.fk(q).translation.copy()        # noqa: E731
    with pytest.raises(HomeRefused, match="leaves the workspace box"):
        p_home = fk(feed.q0)
        plan_home(feed.q0 + OFFSET_RAD, feed.q0, 0.2, 0.05, fk, p_home - 0.01, p_home + 0.01)


def test_reset_world_is_refused_on_a_real_arm():
    pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    feed = Feed("ur")
    ct, _, reply = run_home(feed, {"joint_speed_deg_s": 10.0, "reset_world": True}, feed.q0 + OFFSET_RAD[:6], 0.1)
    assert reply["error"]["code"] == "out_of_limits"
    assert reply["error"]["message"].startswith("reset_world: only the simulated robot has a world to reset")


def until_idle(cli, timeout: float = 10.0) -> None:
    """A task's end is followed by a brake to rest (mode settling) before the next task is taken."""
    deadline = time.monotonic() + timeout
    while cli.command("status")["state"]["mode"] != "idle":
        assert time.monotonic() < deadline, "the arm did not come to rest"
        time.sleep(0.05)


@pytest.mark.slow
def test_after_a_rotate_home_and_a_fresh_world_let_the_next_rotate_work(make_daemon):
    """The simulator could not be reset: after a rotate the next task failed until a restart."""
    d = make_daemon()
    cli = d.client
    first = cli.command("rotate", {"angle_deg": 20})
    assert first["ok"], first
    ev = cli.wait_event(("task_done", "task_failed"), first["task"], 120)
    assert ev["kind"] == "task_done", ev.get("error")
    until_idle(cli)
    home = cli.command("home", {"reset_world": True})
    assert home["ok"], home
    ev = cli.wait_event(("task_done", "task_failed"), home["task"], 120)
    assert ev["kind"] == "task_done", ev
    assert ev["result"]["max_joint_error_deg"] < 0.2
    until_idle(cli)
    again = cli.command("rotate", {"angle_deg": 20})
    assert again["ok"], again
    ev = cli.wait_event(("task_done", "task_failed"), again["task"], 120)
    assert ev["kind"] == "task_done", ev.get("error")
    assert abs(ev["result"]["sim"]["angle_deg"] - 20.0) < 2.0
    assert ev["result"]["sim"]["base_displacement"] < 0.002


@pytest.mark.slow
def test_a_map_that_drags_the_world_fails(make_daemon):
    """`map --grid 2,2` with the cutter's handle in the hand printed "map done" with 0 of 4 points valid
    and the cutter's base dragged 51 mm."""
    d = make_daemon()
    reply = d.client.command("map", {"grid": [2, 2]})
    assert reply["ok"], reply
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 300)
    assert ev["kind"] == "task_failed", ev
    assert "in free air" in ev["error"] and "drags" in ev["error"], ev
    assert ev["sim"]["base_displacement"] < 0.02          # it stopped before the base went far
