"""Who may command the robot: the daemon on mutual TLS with a Zenoh ACL. A client with a certificate
named in zenoh.commanders commands it; one with another certificate from the same CA may watch
but its commands reach nothing; one without a certificate cannot connect at all, and cannot
pose as the daemon either."""
import subprocess
import sys

import pytest

from tecdard.api.client import Client, ClientError
from tecdard.api.session import TlsFiles
from tests.fakes.certs import ScratchCA
from tests.conftest import ROOT

# the slow tier (`make check` leaves it out): whole-daemon runs
pytestmark = pytest.mark.slow

REFUSED_WITHIN_S = 2.0        # a denied query reaches no queryable; the client gives up after this


@pytest.fixture
def pki(tmp_path):
    ca = ScratchCA(tmp_path)
    return ca, {cn: ca.issue(cn) for cn in ("tecdard", "operator", "intruder")}


def files(ca, ident) -> TlsFiles:
    return TlsFiles(str(ca.path), str(ident.cert), str(ident.key))


def test_mtls_and_the_acl_let_only_the_named_client_command(make_daemon, pki):
    ca, ids = pki
    d = make_daemon(protocol="tls", client_tls=files(ca, ids["operator"]),
                    **{"zenoh.tls": {"ca": str(ca.path), "cert": str(ids["tecdard"].cert), "key": str(ids["tecdard"].key)},
                       "zenoh.commanders": ["operator"]})
    op = d.client
    assert op.command("status")["ok"] is True
    assert op.command("cancel")["error"]["code"] == "no_task"          # processed: the daemon answered
    assert op.command("stop")["ok"] is True

    with Client(d.endpoint, tls=files(ca, ids["intruder"])) as intruder:
        intruder.wait_alive(10.0)                                       # it may watch
        assert intruder.states.get(timeout=5.0)["mode"] in ("idle", "stopped")
        for verb, payload in (("stop", None), ("rotate", {"angle_deg": 10.0}), ("status", None)):
            with pytest.raises(ClientError):
                intruder.command(verb, payload, timeout=REFUSED_WITHIN_S)
    assert op.command("status")["state"]["task"] is None                # nothing started

    with Client(d.endpoint) as stranger:                                # no certificate: no session at all
        assert not stranger.alive(1.0)
    # the command line, as an operator types it
    res = subprocess.run([sys.executable, "-m", "tecdard", "status", "--connect", d.endpoint,
                          "--tls-ca", str(ca.path), "--tls-cert", str(ids["operator"].cert),
                          "--tls-key", str(ids["operator"].key), "--json"], capture_output=True, text=True, timeout=60,
                         cwd=ROOT)
    assert res.returncode == 0 and '"ok": true' in res.stdout, res.stderr
    assert d.proc.poll() is None


def test_an_impostor_without_the_cas_certificate_cannot_answer_for_the_daemon(tmp_path, pki):
    """After a crash, an impostor on the daemon's port answered stop with ok: true. A client that
    checks the daemon's certificate against the CA does not talk to it."""
    import zenoh
    from tecdard.tools.demo import free_port
    from tecdard.api.session import Keys, session_config
    ca, ids = pki
    (tmp_path / "rogue").mkdir()
    rogue_ca = ScratchCA(tmp_path / "rogue")
    fake = rogue_ca.issue("tecdard")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    conf = session_config([endpoint], [], tls=TlsFiles(str(rogue_ca.path), str(fake.cert), str(fake.key)))
    with zenoh.open(conf) as session:
        keys = Keys("sim")
        session.declare_queryable(keys.cmd("stop"), lambda q: q.reply(q.key_expr, '{"ok": true}'))
        with Client(endpoint, tls=files(ca, ids["operator"])) as op:
            with pytest.raises(ClientError):
                op.command("stop", timeout=REFUSED_WITHIN_S)


@pytest.mark.parametrize("zenoh_cfg,fragment", [
    ({"zenoh.commanders": ["operator"]}, "zenoh.commanders: needs zenoh.tls"),
    ({"zenoh.listen": ["tls/127.0.0.1:7448"]}, "zenoh.tls: a tls/ endpoint needs zenoh.tls"),
])
def test_security_options_that_cannot_work_are_refused(zenoh_cfg, fragment):
    from tecdard.config import Config, ConfigError
    from tecdard.runtime.daemon import Daemon
    from tests.conftest import sim_config
    with pytest.raises(ConfigError, match=fragment):
        Daemon(Config(sim_config(**zenoh_cfg)))


def test_tls_beside_a_plain_endpoint_is_refused(pki):
    from tecdard.config import Config, ConfigError
    from tecdard.runtime.daemon import Daemon
    from tests.conftest import sim_config
    ca, ids = pki
    cfg = sim_config(**{"zenoh.tls": {"ca": str(ca.path), "cert": str(ids["tecdard"].cert),
                                      "key": str(ids["tecdard"].key)},
                        "zenoh.listen": ["tls/127.0.0.1:7448", "tcp/127.0.0.1:7449"]})
    with pytest.raises(ConfigError, match="is not a tls/ endpoint"):
        Daemon(Config(cfg))
    cfg["zenoh"]["listen"] = ["tls/127.0.0.1:7448"]
    cfg["zenoh"]["tls"]["key"] = str(ca.path.parent / "missing.key")
    with pytest.raises(ConfigError, match="zenoh.tls.key: cannot read"):
        Daemon(Config(cfg))
