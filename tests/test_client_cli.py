"""The client verbs against a running daemon: exit codes, refusals, following a task to the end."""
import json

from tests.conftest import tecdard


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
    from tecdard.tools.demo import free_port
    res = tecdard("status", "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "2")
    assert res.returncode == 3
    assert "not alive" in res.stderr


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
    assert "not alive" in capsys.readouterr().err


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
        status = tecdard("status", "--connect", router_ep)
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
        assert [field for _opt, field, _t, _h in options[verb]] == [f.name for f in C.task_verbs_registry.get(verb).fields]
    parser = argparse.ArgumentParser()
    client_cli.add_parsers(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["rotate", "--angle-deg", "10", "--no-turn-tool"])
    assert args.turn_tool is False
    assert parser.parse_args(["rotate", "--angle-deg", "10"]).turn_tool is None      # the daemon's default
