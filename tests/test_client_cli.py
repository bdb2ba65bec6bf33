"""The client verbs against a running daemon: exit codes, refusals, following a task to the end."""
import json
import subprocess
import sys

from tests.conftest import ROOT


def tecdard(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "tecdard", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def test_verbs_against_a_daemon(shared_daemon):
    ep = shared_daemon.endpoint
    status = tecdard("status", "--connect", ep)
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


def test_no_daemon_is_exit_3(tmp_path):
    from tecdard.demo import free_port
    res = tecdard("status", "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "2")
    assert res.returncode == 3
    assert "not alive" in res.stderr
