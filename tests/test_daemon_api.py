"""The daemon's Zenoh interface at rest, against one daemon for the module: status, the state stream,
and bad commands refused without motion. (A module of its own: the shared daemon and its simulated
arm live until the module ends, and must not run beside the whole-daemon task tests.)"""
import time

import numpy as np
import pytest

from tests.conftest import STILL_M, tcp_now

# the slow tier (`make check` leaves it out): whole-daemon runs
pytestmark = pytest.mark.slow


def test_status_state_and_events_follow_the_spec(shared_daemon):
    cli = shared_daemon.client
    reply = cli.command("status")
    assert reply["ok"] is True
    state = reply["state"]
    assert set(state) >= {"t", "seq", "mode", "tcp", "contact", "task", "faults"}
    assert state["mode"] == "idle"
    assert set(state["tcp"]) == {"p", "q", "v"}
    assert abs(np.linalg.norm(state["tcp"]["q"]) - 1.0) < 1e-6
    assert state["control"]["planner_fallbacks"] == 0 and state["control"]["ticks"] > 0
    assert state["imu"]["part"] == "LSM6DSR (simulated)"
    # state streams at the tick rate
    time.sleep(0.5)
    seqs = []
    while not cli.states.empty():
        seqs.append(cli.states.get()["seq"])
    assert len(seqs) >= 10 and seqs == sorted(seqs)


@pytest.mark.parametrize("verb,payload,code,field", [
    ("rotate", "{broken", "bad_json", "payload"),
    ("rotate", "{}", "missing_field", "angle_deg"),
    ("rotate", '{"angle_deg": "30"}', "bad_type", "angle_deg"),
    ("rotate", '{"angle_deg": 170}', "out_of_limits", "angle_deg"),
    ("rotate", '{"angle_deg": 30, "speed": 1.0}', "out_of_limits", "speed"),
    ("probe", '{"direction": [1, 1, 1]}', "out_of_limits", "direction"),
    ("fly", "{}", "unknown_verb", "fly"),
    ("point", '{"radius": 0.2}', "out_of_limits", "radius"),
    ("point", '{"turns": 1, "direction": [1, 0, 0]}', "unknown_field", "direction"),
    ("map", '{"origin": [3.0, 0.0]}', "out_of_limits", "origin"),          # outside the workspace box
    ("map", '{"grid": [2, 2.5]}', "bad_type", "grid"),
    ("cancel", "{}", "no_task", "task"),
])
def test_bad_commands_are_refused_without_motion(shared_daemon, verb, payload, code, field):
    cli = shared_daemon.client
    before = tcp_now(cli)
    reply = cli.command(verb, payload)
    assert reply["ok"] is False
    assert reply["error"]["code"] == code
    assert field in reply["error"]["message"]
    time.sleep(0.1)
    assert np.linalg.norm(tcp_now(cli) - before) < STILL_M
    assert cli.command("status")["state"]["mode"] == "idle"
    assert shared_daemon.proc.poll() is None
