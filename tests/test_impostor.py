"""No other process answers for the daemon (issue 32, item 3).

The red team's setup: mutual TLS with `commanders: [operator]`, and a peer with a valid certificate
named `watcher` that listens on an endpoint of its own and connects to the daemon. A peer-mode
client learned the watcher's address by gossip, connected to it, and took its answers to `status`,
`rotate` and `stop`, its forged `task_done`, and its liveliness token after the daemon had gone.
The same worked on loopback without TLS while the daemon ran. Here the impostors try again:
- a peer on its own endpoint, connected to the daemon (gossip's way in);
- a client of the daemon's own endpoint, with a queryable on `**` (routing's way in);
- the watcher on the daemon's port once the daemon has exited (with TLS).
"""
import time

import pytest
import zenoh

from tecdard.api.session import Keys, TlsFiles, session_config
from tecdard.api.client import Client, ClientError
from tecdard.tools.demo import free_port
from tests.fakes.certs import ScratchCA

FORGED = '{"t": 0.0, "kind": "task_done", "task": "forged", "result": {}}'
NO_ANSWER_S = 1.5
SETTLE_S = 1.0               # the impostors' declarations have spread


def impostor(keys: Keys, listen: list[str], connect: list[str], tls=None, mode: str = "peer"):
    """A session that answers every command with ok, holds the daemon's token and forges events."""
    conf = session_config(listen, connect, tls=tls, mode=mode)
    if mode == "client":
        conf.insert_json5("connect/timeout_ms", '{"client": 5000}')
    session = zenoh.open(conf)

    def answer(query):
        if str(query.key_expr).startswith(keys.cmd_prefix):
            query.reply(query.key_expr, '{"ok": true, "task": "forged", "who": "impostor"}')
    held = [session.declare_queryable(keys.cmd_all, answer), session.declare_queryable("**", answer),
            session.liveliness().declare_token(keys.alive)]
    return session, held


def forge(sessions, keys: Keys) -> None:
    for s in sessions:
        s.put(keys.events, FORGED)


def assert_only_the_daemon_answers(client: Client, keys: Keys, impostors) -> None:
    status = client.command("status")
    assert status["ok"] is True and "state" in status, status
    refused = client.command("rotate", {"angle_deg": 1000.0})
    assert refused["ok"] is False and refused["error"]["code"] == "out_of_limits", refused
    assert client.command("cancel")["error"]["code"] == "no_task"
    forge(impostors, keys)
    time.sleep(0.5)
    assert not any(ev.get("task") == "forged" for ev in client.event_log), client.event_log


@pytest.fixture
def pki(tmp_path):
    ca = ScratchCA(tmp_path)
    ids = {cn: ca.issue(cn) for cn in ("tecdard", "operator", "watcher")}
    return lambda cn: TlsFiles(str(ca.path), str(ids[cn].cert), str(ids[cn].key))


@pytest.mark.slow
def test_with_tls_a_watcher_never_answers_for_the_daemon_before_or_after_it_exits(make_daemon, pki):
    keys = Keys("sim")
    d = make_daemon(protocol="tls", client_tls=pki("operator"),
                    **{"zenoh.tls": {"ca": pki("tecdard").ca, "cert": pki("tecdard").cert, "key": pki("tecdard").key},
                       "zenoh.commanders": ["operator"]})
    own = f"tls/127.0.0.1:{free_port()}"
    peer, _ = impostor(keys, [own], [d.endpoint], tls=pki("watcher"))
    client_of_daemon, _ = impostor(keys, [], [d.endpoint], tls=pki("watcher"), mode="client")
    try:
        time.sleep(SETTLE_S)
        with Client(d.endpoint, tls=pki("operator")) as op:
            assert_only_the_daemon_answers(op, keys, [peer, client_of_daemon])
            assert op.command("stop")["ok"] is True
            # the daemon exits: nothing is alive, and nothing answers a command
            assert d.terminate() == 0
            assert not op.alive(1.0)
            with pytest.raises(ClientError):
                op.command("rotate", {"angle_deg": 10.0}, timeout=NO_ANSWER_S)
            assert not any(ev.get("task") == "forged" for ev in op.event_log)
        # the watcher takes the daemon's port: its certificate is not the daemon's
        client_of_daemon.close()
        peer.close()
        takeover, _ = impostor(keys, [d.endpoint], [], tls=pki("watcher"))
        try:
            with Client(d.endpoint, tls=pki("operator")) as op:
                assert not op.alive(1.0)
                with pytest.raises(ClientError):
                    op.command("rotate", {"angle_deg": 10.0}, timeout=NO_ANSWER_S)
            # a client told the watcher's name does reach it: the name is what was checked
            with Client(d.endpoint, tls=pki("operator"), daemon_name="watcher") as op:
                assert op.alive(2.0)
        finally:
            takeover.close()
    finally:
        for s in (peer, client_of_daemon):
            try:
                s.close()
            except Exception:
                pass


@pytest.mark.slow
def test_on_loopback_no_impostor_answers_while_the_daemon_runs(make_daemon):
    keys = Keys("sim")
    d = make_daemon()
    own = f"tcp/127.0.0.1:{free_port()}"
    peer, _ = impostor(keys, [own], [d.endpoint])
    client_of_daemon, _ = impostor(keys, [], [d.endpoint], mode="client")
    try:
        time.sleep(SETTLE_S)
        with Client(d.endpoint) as cli:
            assert_only_the_daemon_answers(cli, keys, [peer, client_of_daemon])
            # the client reached the daemon's endpoint and nothing else
            assert len(list(cli.session.info.peers_zid())) + len(list(cli.session.info.routers_zid())) == 1
            assert d.terminate() == 0
            assert not cli.alive(1.0)                   # the impostors' tokens never reach it
            with pytest.raises(ClientError):
                cli.command("status", timeout=NO_ANSWER_S)
    finally:
        peer.close()
        client_of_daemon.close()


def test_the_daemons_access_control_keeps_other_sessions_off_its_keys():
    """What a third-party client relies on: through the daemon, only the daemon publishes, answers
    and holds a token on tecdar/{robot}/**, whatever key another session declares on."""
    from tecdard.api.session import access_control
    acl = access_control(Keys("sim"), None)
    ingress = {m for r in acl["rules"] if "ingress" in r["flows"] for m in r["messages"]}
    assert ingress == {"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"}
    assert acl["default_permission"] == "deny"


@pytest.mark.slow
def test_a_unix_socket_in_the_daemons_own_directory_serves_clients(make_daemon, tmp_path):
    """The loopback endpoint no other user can take: a socket in a directory only the daemon's
    user may write (docs/zenoh-api.md, Reaching only the daemon)."""
    import os
    import stat
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    d = make_daemon(endpoint=f"unixsock-stream/{run / 'tecdar.sock'}")
    assert stat.S_IMODE(os.stat(run).st_mode) == 0o700
    assert d.client.command("status")["ok"] is True
