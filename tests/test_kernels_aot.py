"""Issue 37: the kernels built ahead of time (control/estimators/kernels/build.py) are the JIT's answers,
to the last digit, in a process that never imports numba; a stale or missing build falls back to the JIT."""
import json
import os
import subprocess
import sys

import pytest

from tecdard.control.estimators.kernels import api, build
from tests.conftest import ROOT
from tests.test_localize import scenario_file

# a probe that reports what the estimators run on and whether numba or LLVM was loaded for it
PROBE = ("import sys, json; from tecdard.control.estimators.kernels import api; "
         "print(json.dumps([api.KIND, api.WHY, 'numba' in sys.modules, 'llvmlite' in sys.modules]))")


def probe(**env):
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, cwd=ROOT,
                         env={**os.environ, **env})
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_install_built_them_and_loading_them_imports_no_numba():
    """`make` ran `tecdard warm`: the build is current, and the estimators load it without numba or LLVM."""
    assert build.aot_problem() is None
    assert probe() == ["aot", None, False, False]
    assert api.KIND == "aot"


@pytest.mark.slow
def test_jit_on_request_and_aot_refused_when_it_cannot_be_had(monkeypatch):
    assert probe(TECDAR_KERNELS="jit") == ["jit", "TECDAR_KERNELS=jit", True, True]
    monkeypatch.setattr(build, "DIGEST_FILE", os.path.join(os.path.dirname(build.DIGEST_FILE), "none.digest"))
    assert build.aot_problem() == "not built (`tecdard warm` builds it)"
    monkeypatch.setattr(build, "source_digest", lambda: "another")
    monkeypatch.setattr(build, "DIGEST_FILE", build.HERE + "/" + build.MODULE + ".digest")
    assert "built from other sources" in build.aot_problem()
    monkeypatch.setenv("TECDAR_KERNELS", "aot")
    with pytest.raises(ImportError, match="TECDAR_KERNELS=aot, but the ahead-of-time kernels are built from other"):
        api._load()


def test_the_extension_releases_the_gil():
    """The exports are compiled with release_gil (pycc's default holds it): the module calls
    PyEval_SaveThread around each kernel, as the JIT's nogil=True does."""
    import importlib.util
    so = importlib.util.find_spec(f"{api.__package__}.{build.MODULE}").origin
    syms = subprocess.run(["nm", "-D", "--undefined-only", so], capture_output=True, text=True).stdout
    assert "PyEval_SaveThread" in syms and "PyEval_RestoreThread" in syms


@pytest.mark.slow
@pytest.mark.parametrize("kind,seed", [("edge-arc", 3), ("hinge", 7)])
def test_localize_gives_the_jits_answer_to_the_last_digit(tmp_path, kind, seed):
    """The whole estimator through `tecdard localize`, once on the build and once on numba's JIT:
    every row and the summary are the same text."""
    rec = scenario_file(tmp_path / "r.npz", kind=kind, seed=seed, duration_s=0.8, planar=kind != "hinge")
    outs = []
    for mode in ("aot", "jit"):
        csv = tmp_path / f"{mode}.csv"
        res = subprocess.run([sys.executable, "-m", "tecdard", "localize", str(rec), "--out", str(csv), "--json"],
                             capture_output=True, text=True, timeout=180, cwd=ROOT,
                             env={**os.environ, "TECDAR_KERNELS": mode})
        assert res.returncode == 0, res.stderr
        outs.append((res.stdout, csv.read_text()))
    assert outs[0][0] == outs[1][0] and json.loads(outs[0][0])["method"] == "ekf"
    assert outs[0][1] == outs[1][1] and outs[0][1].count("\n") > 100


MDWE = ("import ctypes, os, sys; assert ctypes.CDLL(None).prctl(65, 1, 0, 0, 0) == 0, 'no PR_SET_MDWE'; "
        "os.execv(sys.executable, [sys.executable, '-m', 'tecdard', 'run', '--config', sys.argv[1]])")


@pytest.mark.slow
def test_the_daemon_runs_where_memory_may_not_be_written_and_executed(tmp_path):
    """The unit's MemoryDenyWriteExecute, as the kernel's PR_SET_MDWE (what systemd sets on Linux 6.3+,
    inherited across exec): a daemon on the built kernels opens the cutter; one that would need
    numba's JIT there refuses to start in one line (exit 2) instead of failing mid-task."""
    import types
    from tecdard.api.client import Client
    from tests.conftest import daemon_config, dump_yaml, free_port, rotate_on_the_cutter
    cfg = daemon_config()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg["zenoh"]["listen"] = [endpoint]
    cfg.setdefault("record", {})["dir"] = str(tmp_path / "recordings")
    config = tmp_path / "tecdard.yaml"
    config.write_text(dump_yaml(cfg))
    jit = subprocess.run([sys.executable, "-c", MDWE, str(config)], capture_output=True, text=True, timeout=120,
                         cwd=ROOT, env={**os.environ, "TECDAR_KERNELS": "jit"})
    lines = jit.stderr.strip().splitlines()
    assert jit.returncode == 2 and len(lines) == 1, jit.stderr
    assert "not built ahead of time (TECDAR_KERNELS=jit)" in lines[0] and "MemoryDenyWriteExecute" in lines[0]
    log = open(tmp_path / "daemon.log", "w")
    proc = subprocess.Popen([sys.executable, "-c", MDWE, str(config)], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    try:
        client = Client(endpoint, robot=cfg["robot"]["name"])
        client.wait_alive(60.0, running=lambda: proc.poll() is None)
        d = types.SimpleNamespace(client=client, log=lambda: (tmp_path / "daemon.log").read_text())
        assert rotate_on_the_cutter(d, 15.0) < 0.005
        maps = open(f"/proc/{proc.pid}/maps").read().splitlines()
        assert not [m for m in maps if m.split()[1].startswith("rwx")]
    finally:
        proc.terminate()
        proc.wait(30)
        log.close()
