"""Whole daemon against hostile or careless clients: payloads that crashed it, floods during a task,
and stop under load. Each test runs its own daemon."""
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.conftest import ROOT, STILL_M, tcp_now
from tests.test_daemon import TASK_TIMEOUT_S, assert_arc_opened_the_cutter

# the slow tier (`make check` leaves it out): whole-daemon runs
pytestmark = pytest.mark.slow

# Braking from 20 mm/s at 0.5 m/s^2 takes about 0.1 s, and a stop is taken at the next 20 ms tick;
# this much more allows a loaded shared machine. The red team's stop took 8.7 s under load.
STOP_REPLY_MAX_S = 1.0
# At rest the reply follows the next tick (20 ms); measured 4-36 ms under this flood (benchmarks/hostile.md).
STOP_AT_REST_MAX_S = 0.2
SIGKILL_AFTER_STOP_S = 0.01     # the stop starts the map's write at the next tick; it takes ~50-100 ms
RED_TEAM_QUERIES = 12_040      # the flooder's first round: 40 payloads of 10 MB and 12 000 status queries
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
    reply = paced(cli, "probe", {"direction": [0.0, 0.0, 1.0]})     # the task class's budget was just spent
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
    return subprocess.Popen(["nice", "-n", str(FLOOD_NICE), sys.executable, "-m", "tests.fakes.flood", endpoint,
                             str(seconds)], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})


@pytest.mark.alone      # the flooder runs at nice 19: beside another worker's daemon it does not flood
def test_a_flood_during_a_task_neither_ends_it_nor_delays_stop(make_daemon):
    d = make_daemon()
    cli = d.client
    reply = cli.command("rotate", {"angle_deg": 30.0})
    assert reply["ok"] is True, reply
    flooder = flood(d.endpoint, 60.0)          # its 40 payloads of 10 MB arrive during the rotate's probe
    try:
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
        # at rest a stop is taken at the next tick and answered at once, flood or not
        for _ in range(10):
            t0 = time.monotonic()
            assert cli.command("stop", timeout=10.0)["ok"] is True
            took = time.monotonic() - t0
            assert took < STOP_AT_REST_MAX_S, f"stop at rest answered after {took * 1e3:.0f} ms"
        assert not [e for e in cli.event_log if e["kind"] == "fault"], cli.event_log
    finally:
        flooder.terminate()
        out, _ = flooder.communicate(timeout=10)
    assert int(out.strip() or 0) >= RED_TEAM_QUERIES, "the flood did not flood"
    assert d.proc.poll() is None
    assert "Traceback" not in d.log()


# -- data loss: signals during a map --------------------------------------------------------------
def map_daemon(make_daemon, tmp_path):
    """A daemon over the box scene of the map test, and a 2 x 2 map started on it."""
    from tests.test_daemon import MAP_SCENE
    tilt, tool_m = np.radians(30.0), 0.12
    tip_tcp = [float(tool_m * np.sin(tilt)), 0.0, float(tool_m * np.cos(tilt))]
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": tip_tcp, "surface": "boxes", **MAP_SCENE},
                       "map": {"output_dir": str(tmp_path / "maps"), "tool_tip_tcp": tip_tcp},
                       "control.imu_stale_s": 0.25})
    reply = d.client.command("map", {"origin": [0.32, -0.04], "size": [0.08, 0.08], "grid": [2, 2], "depth": 0.06,
                                     "orientations": 1, "speed": 0.02})
    assert reply["ok"] is True, reply
    return d, reply["task"]


def wait_for_points(d, task: str, n: int, timeout: float = TASK_TIMEOUT_S) -> None:
    """Until the map has probed n points (its progress says so)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        state = latest_state(d.client)
        if state["task"] and state["task"]["id"] == task and state["task"]["progress"] >= n / 4 - 1e-6:
            return
    raise AssertionError(f"{task}: fewer than {n} points within {timeout} s\n{d.log()[-2000:]}")


def complete_maps(out_dir) -> dict:
    """task id -> its map's four files, for each directory a reader may see (no hidden partials);
    each must be whole: depth.npy loads, points.csv and summary.json parse, depth.png is a PNG."""
    import csv
    maps = {}
    for m in sorted(p for p in out_dir.iterdir() if not p.name.startswith(".")):
        names = sorted(f.name for f in m.iterdir())
        assert names == ["depth.npy", "depth.png", "points.csv", "summary.json"], (m, names)
        np.load(m / "depth.npy")
        json.loads((m / "summary.json").read_text())
        rows = list(csv.DictReader(open(m / "points.csv")))
        assert (m / "depth.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        maps[m.name] = rows
    return maps


def test_sigterm_during_a_map_saves_what_stop_saves(make_daemon, tmp_path):
    """systemd's stop and restart send SIGTERM: the map is stopped as `stop` stops it, its points
    are written, and only then does the daemon exit (0)."""
    import signal
    d, task = map_daemon(make_daemon, tmp_path)
    wait_for_points(d, task, 1)
    assert d.terminate(signal.SIGTERM, timeout=10.0) == 0
    maps = complete_maps(tmp_path / "maps")
    assert list(maps) == [task] and len(maps[task]) >= 1
    log = d.log()
    assert "daemon shutting down" in log and '"kind":"map_written"' in log, log[-2000:]


def test_sigkill_while_a_map_is_written_leaves_it_whole_or_absent(make_daemon, tmp_path):
    """The map's files go into a hidden partial directory that is renamed when complete: a kill at
    any moment of the write leaves the map whole, or nothing under its name; the next start removes
    the partial leftovers."""
    import signal
    d, task = map_daemon(make_daemon, tmp_path)
    wait_for_points(d, task, 1)
    d.client.session.get(d.client.keys.cmd("stop"), timeout=1.0)       # the stop writes the points so far
    time.sleep(SIGKILL_AFTER_STOP_S)
    d.proc.send_signal(signal.SIGKILL)
    d.proc.wait(10.0)
    out = tmp_path / "maps"
    assert set(complete_maps(out)) <= {task}
    from tecdard.files import ensure_writable_dir
    ensure_writable_dir(out, "map.output_dir")                          # what the next start does
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_a_megabyte_payload_is_refused_with_a_reply_every_time(make_daemon):
    """A 1 MB payload got no reply at all, a timeout (issue 32, item 11): the transport dropped a
    mebibyte, and a payload under it cost the task class its whole budget, so the next one was
    rate_limited. A refusal that costs nothing to send is sent."""
    d = make_daemon()
    for size in (1_000_000, 1 << 20):
        for verb in ("status", "rotate", "record", "nonsense"):
            for _ in range(3):
                t0 = time.monotonic()
                reply = d.client.command(verb, "x" * size, timeout=5.0)
                assert reply["ok"] is False and reply["error"]["code"] == "payload_too_large", (size, verb, reply)
                assert time.monotonic() - t0 < 2.0
    assert d.proc.poll() is None


def test_a_record_flood_neither_starves_other_verbs_nor_fills_the_disk(make_daemon, tmp_path):
    """One client's record start/stop flood served another client's rotate 2 times in 20 and wrote
    91 files in 20 s (issue 32, item 10): record has a class of its own, and captures on demand a
    rate and count limit."""
    import threading

    from tecdard.api.client import Client
    d = make_daemon()
    stop = threading.Event()
    sent = [0]

    def flood():
        with Client(d.endpoint) as flooder:
            while not stop.is_set():
                for action in ("start", "stop"):
                    try:
                        flooder.command("record", {"action": action, "label": "flood"}, timeout=1.0)
                    except Exception:
                        pass
                    sent[0] += 1
    th = threading.Thread(target=flood, daemon=True)
    th.start()
    try:
        time.sleep(0.5)
        served = []
        for _ in range(20):
            served.append(d.client.command("rotate", {"angle_deg": 1000.0}, timeout=5.0)["error"]["code"])
            time.sleep(0.2)
    finally:
        stop.set()
        th.join(5.0)
    assert served == ["out_of_limits"] * 20, served
    time.sleep(1.0)
    files = [f for f in os.listdir(d.config_path.parent / "recordings") if not f.startswith(".")]
    print(f"{sent[0]} record queries sent; {len(files)} files written")
    assert sent[0] > 40 and len(files) <= 11, (sent[0], files)


def test_ctrl_c_to_the_daemons_process_group_holds_the_arm_and_logs_no_traceback(tmp_path):
    """Issue 50 item 15: `tecdard run` in a terminal, then Ctrl-C. The terminal signals the whole foreground
    process group: the simulation's process died of KeyboardInterrupt under the daemon, whose hold on exit
    then failed twice, and the log carried three tracebacks around "tecdard stopped". The daemon's
    children now leave SIGINT to it: it holds the arm, then closes them."""
    import signal
    from tests.conftest import DaemonProcess, daemon_config
    d = DaemonProcess(tmp_path, daemon_config(), own_group=True)
    try:
        reply = d.client.command("rotate", {"angle_deg": 30.0})
        assert reply["ok"] is True, reply
        deadline = time.monotonic() + TASK_TIMEOUT_S      # into the arc: the simulation is busiest there
        while (d.client.command("status")["state"].get("task") or {}).get("phase") != "arc":
            assert time.monotonic() < deadline, d.log()[-3000:]
            time.sleep(0.05)
        os.killpg(d.proc.pid, signal.SIGINT)
        assert d.proc.wait(15.0) == 0, d.log()[-3000:]
    finally:
        d.close()
    log = d.log()
    assert "Traceback" not in log and " ERROR " not in log, log[-4000:]
    assert log.rstrip().endswith("tecdard stopped"), log[-2000:]
    assert '"error":"daemon shutting down"' in log, log[-2000:]
