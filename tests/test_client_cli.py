"""The client verbs against a running daemon: exit codes, refusals, following a task to the end."""
import json

import pytest

from tests.conftest import tecdard

# the slow tier (`make check` leaves it out): the command line against a running daemon
pytestmark = pytest.mark.slow


def test_verbs_against_a_daemon(shared_daemon):
    ep = shared_daemon.endpoint
    status = tecdard("status", "--connect", ep, "--json")
    assert status.returncode == 0
    assert json.loads(status.stdout)["state"]["mode"] == "idle"
    refused = tecdard("rotate", "--connect", ep, "--angle-deg", "500")
    assert refused.returncode == 2
    assert "out_of_limits" in refused.stderr and "angle_deg" in refused.stderr
    missing = tecdard("rotate", "--connect", ep)
    assert missing.returncode == 2 and "missing_field" in missing.stderr
    bad_grid = tecdard("map", "--connect", ep, "--grid", "0,6")
    assert bad_grid.returncode == 2 and "out_of_limits" in bad_grid.stderr and "grid" in bad_grid.stderr
    assert tecdard("cancel", "--connect", ep).returncode == 2       # no task to cancel
    done = tecdard("rotate", "--connect", ep, "--angle-deg", "10", "--json")
    assert done.returncode == 0, done.stderr
    events = [json.loads(line) for line in done.stdout.splitlines()]
    assert events[0]["ok"] is True and events[-1]["kind"] == "task_done"
    assert abs(events[-1]["result"]["sim"]["angle_deg"] - 10.0) < 2.0
    assert tecdard("stop", "--connect", ep).returncode == 0


def test_a_client_leaves_no_thread_that_would_keep_the_process_from_exiting(shared_daemon):
    """A test run once printed its summary and never exited (CI's 90 minutes ran out): three of
    zenoh-python's callback threads, which are not daemon threads, outlived their client's session.
    The client's subscribers run on Zenoh's own threads: it starts no Python thread at all."""
    import threading
    from tecdard.api.client import Client
    before = set(threading.enumerate())
    with Client(shared_daemon.endpoint) as cli:
        assert cli.command("status")["state"]["mode"] == "idle"
        assert cli.states.get(timeout=5.0)["seq"] > 0            # its subscribers receive
        started = [t.name for t in set(threading.enumerate()) - before if not t.daemon]
    assert started == []


def test_no_daemon_is_exit_3(tmp_path):
    from tecdard.tools.demo import free_port
    res = tecdard("status", "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "2")
    assert res.returncode == 3
    assert "connection refused" in res.stderr          # nothing listens there: said at once


def test_negative_vectors_work_as_typed(capsys):
    """Issue 17: `--direction -0.26,0,0.96` was `expected one argument`; only `--direction=-0.26,...` worked."""
    from tecdard.cli.main import join_negative_values, main
    assert join_negative_values(["probe", "--direction", "-0.26,0,0.96", "--speed", "0.01"]) == \
        ["probe", "--direction=-0.26,0,0.96", "--speed", "0.01"]
    assert join_negative_values(["map", "--origin", "-.3,-0.1", "--json"]) == ["map", "--origin=-.3,-0.1", "--json"]
    assert join_negative_values(["status", "--json", "--timeout", "2"]) == ["status", "--json", "--timeout", "2"]
    from tecdard.tools.demo import free_port
    # parsed, then no daemon there: exit 3, not argparse's exit 2
    assert main(["probe", "--direction", "-0.26,0,0.96", "--connect", f"tcp/127.0.0.1:{free_port()}",
                 "--timeout", "0.5"]) == 3
    assert "connection refused" in capsys.readouterr().err


def test_the_default_endpoint_is_not_zenohs_router_port():
    """7447 is zenohd's and rmw_zenohd's default: a daemon there could not listen beside a router."""
    from tecdard.api.session import DEFAULT_ENDPOINT
    from tecdard.cli import task_verbs
    from tests.conftest import sim_config
    assert task_verbs.DEFAULT_ENDPOINT == DEFAULT_ENDPOINT == sim_config()["zenoh"]["listen"][0]
    assert not DEFAULT_ENDPOINT.endswith(":7447")


def test_the_cli_reaches_the_daemon_through_a_local_zenoh_router(make_daemon):
    """A Zenoh router on the host (as zenohd or ROS 2's rmw_zenohd runs one): the daemon is its
    client and listens on nothing, and the CLI, connected to the router only, commands it."""
    import zenoh
    from tecdard.tools.demo import free_port
    from tecdard.api.session import session_config
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(session_config([router_ep], [], mode="router")):
        d = make_daemon(router=router_ep)
        assert "Zenoh client" in d.log() and "connecting to " + router_ep in d.log()
        status = tecdard("status", "--connect", router_ep, "--json")
        assert status.returncode == 0, status.stderr
        assert json.loads(status.stdout)["state"]["mode"] == "idle"
        refused = tecdard("probe", "--connect", router_ep, "--direction", "-0.26,0,0.96", "--distance", "5")
        assert refused.returncode == 2 and "out_of_limits" in refused.stderr
        assert tecdard("stop", "--connect", router_ep).returncode == 0


def test_the_cli_offers_every_task_verb_and_rotates_with_the_tool_held():
    """The CLI once took its verb list from a copy, and lacked rotate's turn_tool: its options now come
    from the verbs' registered fields."""
    import argparse
    from tecdard.cli import task_verbs as client_cli
    from tecdard.api import commands as C
    options = client_cli.verb_options()
    assert set(C.verbs()) == set(options)
    for verb in C.task_verbs():
        fields = [f.name for f in C.task_verbs_registry.get(verb).fields]
        assert [field for _opt, field, _t, _h, _c in options[verb]] == fields
    parser = argparse.ArgumentParser()
    client_cli.add_parsers(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["rotate", "--angle-deg", "10", "--no-turn-tool"])
    assert args.turn_tool is False
    assert parser.parse_args(["rotate", "--angle-deg", "10"]).turn_tool is None      # the daemon's default


# -- issue 33: Ctrl-C, --timeout, one-line errors, output for people ------------------------------

def _cli(*args, env=None):
    """The command line as a process of its own, with Ctrl-C's default (a shell's background job has
    SIGINT ignored, which Python would keep)."""
    import os
    import signal
    import subprocess
    import sys
    from tests.conftest import ROOT
    return subprocess.Popen([sys.executable, "-m", "tecdard", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, **(env or {})},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _still(cli, seconds=0.5) -> float:
    """How far the TCP moves in `seconds` (m)."""
    import time
    import numpy as np
    from tests.conftest import tcp_now
    p0 = tcp_now(cli)
    time.sleep(seconds)
    return float(np.linalg.norm(tcp_now(cli) - p0))


def _wait_for_line(proc, text: str, timeout: float = 60.0) -> list[str]:
    import time
    lines, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no {text!r} from the CLI: {lines}")


@pytest.mark.slow
def test_ctrl_c_cancels_the_task_it_started_and_says_so(make_daemon):
    """Issue 33: `tecdard rotate` then Ctrl-C printed a traceback and the task ran on."""
    import signal
    import time
    from tests.conftest import STILL_M
    d = make_daemon()
    proc = _cli("rotate", "--connect", d.endpoint, "--angle-deg", "30", "--speed", "0.005")
    accepted = _wait_for_line(proc, "accepted as task")[-1]
    task = accepted.split()[-1]
    time.sleep(3.0)                      # the probe has begun: the arm moves
    assert d.client.command("status")["state"]["task"]["id"] == task
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    lines = err.strip().splitlines()
    assert lines[-1] == f"tecdard rotate: interrupted; task {task} cancelled and the arm stopped", err
    assert "Traceback" not in err
    state = d.client.command("status")["state"]
    assert state["mode"] == "idle" and state["task"] is None
    assert _still(d.client) < STILL_M
    assert any(e.get("kind") == "task_failed" and e.get("task") == task for e in d.client.event_log)


@pytest.mark.slow
def test_a_timeout_with_the_task_still_running_cancels_it_and_names_stop(make_daemon):
    from tests.conftest import STILL_M
    d = make_daemon()
    res = tecdard("rotate", "--connect", d.endpoint, "--angle-deg", "30", "--speed", "0.005", "--timeout", "3")
    assert res.returncode == 1, res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("tecdard rotate: still running after --timeout 3 s; task ") and \
        last.endswith("cancelled and the arm stopped"), res.stderr
    assert d.client.command("status")["state"]["mode"] == "idle"
    assert _still(d.client) < STILL_M


@pytest.mark.slow
def test_help_env_status_and_results_read_as_a_person_reads_them(make_daemon):
    """--help shows the running daemon's limits with units and an example; TECDAR_CONNECT and
    TECDAR_ROBOT set the defaults; status and a task's result are tables in mm and degrees; a robot
    name that does not answer is told which do."""
    d = make_daemon(**{"limits.max_rotation_deg": 45.0})
    env = {"TECDAR_CONNECT": d.endpoint, "TECDAR_ROBOT": "sim"}
    proc = _cli("rotate", "--help", env=env)
    out, _ = proc.communicate(timeout=60)
    flat = " ".join(out.split())
    assert "limits 0.1..45 deg" in flat and "unit m/s" in flat and "default 0.02 m/s" in flat, out
    assert "{arc,straight}" in out and "example: tecdard rotate --angle-deg 30" in out
    assert f"limits: the running daemon's (sim at {d.endpoint})" in out
    proc = _cli("status", env=env)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "mode       idle" in out and " mm" in out and "{" not in out, out
    proc = _cli("status", "--robot", "left-arm", "--wait-alive", "1", env=env)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 3
    assert err.strip().splitlines()[-1].endswith(f"robots that answer at {d.endpoint}: sim (--robot or $TECDAR_ROBOT)")
    proc = _cli("rotate", "--angle-deg", "10", env=env)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "rotate done" in out and "  hinge  " in out and "  angle  " in out and " deg" in out, out
    assert "\x1b" not in err             # not a terminal: whole lines, no escapes


def test_bad_input_on_the_command_line_is_one_line(tmp_path):
    """argparse's usage dumps, NaN in a field, an endpoint without its protocol: one line each."""
    from tecdard.tools.demo import free_port
    port = free_port()
    for args, expect in [
        (("rotate", "--angle-deg", "x"), "tecdard rotate: argument --angle-deg: expected a number, got 'x'"),
        (("rotate", "--angle-deg", "nan"), "tecdard rotate: argument --angle-deg: expected a finite number"),
        (("probe", "--direction", "0,inf,1"), "tecdard probe: argument --direction: expected finite numbers"),
        (("rotate", "--strategy", "spiral", "--angle-deg", "5"), "argument --strategy: invalid choice: 'spiral'"),
        (("status", "--connect", f"127.0.0.1:{port}"), f"tecdard status: --connect 127.0.0.1:{port}: expected "
                                                      "<protocol>/<address>"),
        (("run", "--config", str(tmp_path / "none.yaml")), "tecdard: config error:"),
        (("frobnicate",), "tecdard: argument cmd: invalid choice: 'frobnicate'"),
    ]:
        res = tecdard(*args)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and expect in lines[0], (args, res.stderr)
        assert "usage:" not in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
def test_a_taken_port_says_what_took_it(tmp_path):
    import socket
    from tecdard.config import dump_yaml
    from tests.conftest import sim_config
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        ep = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        path = tmp_path / "tecdard.yaml"
        path.write_text(dump_yaml(sim_config(**{"zenoh.listen": [ep]})))
        res = tecdard("run", "--config", path, timeout=180)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1
    assert lines[-1] == (f"tecdard: {ep}: port {ep.rpartition(':')[2]} is taken: another tecdard? "
                         f"`tecdard status --connect {ep}` (or set zenoh.listen / --listen to a free port)"), res.stderr
    assert ".cargo" not in res.stderr


def test_an_endpoint_where_nothing_listens_is_said_at_once_stop_included(tmp_path):
    """Issue 50 item 11: a wrong endpoint waited 10 s (the liveliness wait), `stop` included; a refused
    connection is said at once. --wait-alive 60 under a 25 s timeout: a wait would not finish in time."""
    from tecdard.tools.demo import free_port
    for verb in ("stop", "status"):
        res = tecdard(verb, "--connect", f"tcp/127.0.0.1:{free_port()}", "--wait-alive", "60", timeout=25)
        assert res.returncode == 3, res.stderr
        assert "(connection refused): is the daemon (or the router) running" in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


def test_a_tls_endpoint_without_certificates_is_said_not_waited_for():
    """Issue 50 item 10, in part: `--connect tls/...` without --tls-* files waited, and read as a dead daemon."""
    for args in (("status",), ("fleet", "status")):
        res = tecdard(*args, "--connect", "tls/127.0.0.1:7447", timeout=25)
        assert res.returncode == 2, res.stderr
        assert "a tls/ endpoint needs --tls-ca, --tls-cert and --tls-key" in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


# -- issue 50 item 15: Ctrl-C, each path one line ------------------------------------------------

def test_a_ctrl_c_that_crosses_the_tasks_end_says_how_it_ended():
    """The Ctrl-C race: the task ended as Ctrl-C was pressed, so the cancel finds no task. The line
    said only "had already ended"; it now says how (the end event the client saw)."""
    from tecdard.api.client import ClientError
    from tecdard.cli import task_verbs

    class Crossed:                          # the daemon's side of the race, as the client sees it
        def __init__(self, end: dict):
            self.event_log = [{"kind": "task_started", "task": "rotate-1"}, end]

        def command(self, verb, payload=None, timeout=None):
            assert verb == "cancel" and payload == {"task": "rotate-1"}
            return {"ok": False, "error": {"code": "no_task", "message": "no task is running"}}

        def wait_event(self, kinds, task=None, timeout=None):
            raise ClientError("no event")

    done = task_verbs._cancel(Crossed({"kind": "task_done", "task": "rotate-1"}), None, "rotate-1", "interrupted")
    assert done == "interrupted; task rotate-1 had already ended: done"
    failed = task_verbs._cancel(Crossed({"kind": "task_failed", "task": "rotate-1", "error": "protective stop: force"}),
                                None, "rotate-1", "interrupted")
    assert failed == "interrupted; task rotate-1 had already ended: failed (protective stop: force)"
    unseen = task_verbs._cancel(Crossed({"kind": "task_started", "task": "other"}), None, "rotate-1", "interrupted")
    assert unseen.endswith("its end event was not seen (`tecdard status`)")


def test_ctrl_c_on_a_verb_without_its_own_handling_is_one_line(monkeypatch, capsys):
    """A verb interrupted where it does not handle Ctrl-C itself (an offline one mid-computation): exit
    130 and one line naming it, no traceback."""
    import argparse
    from tecdard.cli import main as cli_main

    def interrupted(args):
        raise KeyboardInterrupt

    def parser(argv):
        top = argparse.ArgumentParser(prog="tecdard")
        top.add_argument("-v", "--verbose", action="store_true")
        top.add_subparsers().add_parser("localize").set_defaults(func=interrupted)
        return top
    monkeypatch.setattr(cli_main, "parser", parser)
    assert cli_main.main(["-v", "localize"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["tecdard localize: interrupted"]


@pytest.mark.slow
def test_ctrl_c_in_the_demo_cancels_its_task_then_stops_the_daemon():
    """`make run` then Ctrl-C: the terminal's SIGINT reached the demo and its daemon alike, the daemon's
    shutdown failed the task under the demo ("task failed: daemon shutting down") and the demo ended
    in a traceback. The daemon now has a session of its own: the demo cancels its task, says so, and
    stops the daemon (exit 0)."""
    import os
    import re
    import signal
    import subprocess
    import sys
    from tests.conftest import ROOT
    proc = subprocess.Popen([sys.executable, "-m", "tecdard", "demo"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    accepted = _wait_for_line(proc, "accepted as task", timeout=120.0)[-1]
    task = re.search(r"task (\S+);", accepted).group(1)
    os.killpg(proc.pid, signal.SIGINT)      # as a terminal's Ctrl-C: to the demo's whole process group
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, out + err
    assert "Traceback" not in out + err, out + err
    assert f"demo: interrupted; task {task} cancelled (task_failed)" in out, out
    log_path = re.search(r"daemon exit +(\d+) \(log: (\S+)\)", out)
    assert log_path and log_path.group(1) == "0", out
    log = open(log_path.group(2)).read()
    assert "cancelled" in log and "daemon shutting down" not in log, log[-2000:]
