"""Whole daemon against hostile or careless clients: payloads that crashed it, floods during a task,
and stop under load. Each test runs its own daemon."""
import json
import os
import subprocess
import sys
import time

import numpy as np

from tests.conftest import ROOT, STILL_M, tcp_now
from tests.test_daemon import TASK_TIMEOUT_S, assert_arc_opened_the_cutter

# Braking from 20 mm/s at 0.5 m/s^2 takes about 0.1 s, and a stop is taken at the next 20 ms tick;
# this much more allows a loaded shared machine. The red team's stop took 8.7 s under load.
STOP_REPLY_MAX_S = 1.0
FLOOD_NICE = 19              # the flooder runs below the daemon and the simulated arm: the arm and its
                             # board are devices of their own on a real rig, not the attacker's host

CRASH_PAYLOADS = {
    "309 digits": lambda f: json.dumps({f: 0}).replace("0", "9" * 309),
    "4301 digits": lambda f: json.dumps({f: 0}).replace("0", "9" * 4301),
    "overflowing norm": lambda f: json.dumps({f: [1e308, 1e308, 0]}),
    "1000 levels": lambda f: "[" * 1000 + "]" * 1000,
}
VERB_FIELD = {"probe": "distance", "rotate": "angle_deg", "point": "radius", "approach": "direction",
              "map": "depth", "status": "x", "cancel": "task", "stop/now": "x"}


def paced(cli, verb: str, payload) -> dict:
    """A command as a careful client sends it: after a rate_limited reply, again a little later."""
    for _ in range(50):
        reply = cli.command(verb, payload)
        if reply.get("error", {}).get("code") != "rate_limited":
            return reply
        time.sleep(0.2)
    raise AssertionError(f"{verb}: rate limited for 10 s")


def test_the_payloads_that_crashed_the_daemon_are_refused_and_a_task_still_finishes(make_daemon):
    d = make_daemon()
    cli = d.client
    before = tcp_now(cli)
    for verb, field in VERB_FIELD.items():
        for name, make in CRASH_PAYLOADS.items():
            reply = paced(cli, verb, make(field))
            assert reply["ok"] is False, (verb, name, reply)
            assert reply["error"]["code"] in {"bad_json", "bad_type", "out_of_limits", "unknown_verb",
                                              "unknown_field"}, (verb, name, reply)
            assert "\n" not in reply["error"]["message"]
    # a stop stops whatever its payload says, and is answered
    assert cli.command("stop", CRASH_PAYLOADS["1000 levels"]("x"))["ok"] is True
    big = paced(cli, "rotate", "{" + " " * 100_000 + "}")
    assert big["error"]["code"] == "payload_too_large"
    assert np.linalg.norm(tcp_now(cli) - before) < STILL_M
    assert d.proc.poll() is None
    reply = cli.command("probe", {"direction": [0.0, 0.0, 1.0]})
    assert reply["ok"] is True, reply
    ev = cli.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-3000:]}"
    assert "Traceback" not in d.log()


def latest_state(cli) -> dict:
    state = cli.states.get(timeout=1.0)
    while not cli.states.empty():
        state = cli.states.get_nowait()
    return state


def flood(endpoint: str, seconds: float) -> subprocess.Popen:
    return subprocess.Popen(["nice", "-n", str(FLOOD_NICE), sys.executable, "-m", "tests.flood", endpoint,
                             str(seconds)], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_a_flood_during_a_task_neither_ends_it_nor_delays_stop(make_daemon):
    d = make_daemon()
    cli = d.client
    flooder = flood(d.endpoint, 60.0)
    try:
        time.sleep(1.0)
        reply = cli.command("rotate", {"angle_deg": 30.0})
        assert reply["ok"] is True, reply
        ev = cli.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
        assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-3000:]}"
        assert_arc_opened_the_cutter(ev["result"])
        # still flooded: a probe back the way the handle came, stopped in its approach
        reply = cli.command("probe", {"direction": [0.0, 0.0, 1.0], "distance": 0.02, "speed": 0.005})
        assert reply["ok"] is True, reply
        time.sleep(0.5)
        t0 = time.monotonic()
        assert cli.command("stop", timeout=10.0)["ok"] is True
        took = time.monotonic() - t0
        assert took < STOP_REPLY_MAX_S, f"stop answered after {took:.2f} s"
        time.sleep(0.1)
        state = latest_state(cli)       # from the state stream: status itself is what is flooded
        assert state["mode"] == "idle" and state["task"] is None
        assert not [e for e in cli.event_log if e["kind"] == "fault"], cli.event_log
    finally:
        flooder.terminate()
        out, _ = flooder.communicate(timeout=10)
    assert int(out.strip() or 0) > 10_000, "the flood did not flood"
    assert d.proc.poll() is None
    assert "Traceback" not in d.log()
