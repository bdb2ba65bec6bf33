"""Issues 17 and 37: the estimator's kernels are built ahead of time at install (else cached by numba's JIT),
and a start that must compile says so."""
import logging
import os
import pickle

import numba
import pytest
from numba.core import config as numba_config

from tecdard.control.estimators.kernels import build
from tecdard.tools import kernel_cache


@pytest.fixture
def no_build(monkeypatch):
    """As if the kernels had not been built ahead of time: the JIT's cache decides."""
    monkeypatch.setattr(build, "aot_problem", lambda: "not built (`tecdard warm` builds it)")


def test_the_installed_kernels_are_built_and_the_jits_cache_is_warm():
    """`make` ran `tecdard warm --jit`: a start loads the build, and every kernel of
    control/estimators/kernels/ loads from numba's cache where the tests import them."""
    state = kernel_cache.state()
    assert state.aot and state.warm and state.path.endswith(".so"), state
    assert "compiled ahead of time" in state.describe() and "nothing compiles" in state.describe()
    jit = kernel_cache.jit_state()
    assert jit.expected >= 20 and jit.warm and jit.fresh == jit.expected, jit
    assert "cached in" in jit.describe()


def test_an_empty_cache_is_cold_and_the_start_says_so(tmp_path, monkeypatch, caplog, no_build):
    monkeypatch.setattr(numba_config, "CACHE_DIR", str(tmp_path))      # what NUMBA_CACHE_DIR sets
    state = kernel_cache.state()
    assert not state.warm and state.fresh == 0 and state.path.startswith(str(tmp_path))
    assert "this start compiles them, about 90 s" in state.describe()
    with caplog.at_level(logging.INFO, logger="tecdar"):
        kernel_cache.announce_compile()
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1 and "compiles" in lines[0] and str(tmp_path) in lines[0]


def test_an_entry_numba_would_not_load_is_not_counted(tmp_path, monkeypatch):
    """Another numba version, or the source changed since (its stamp): numba compiles again."""
    monkeypatch.setattr(numba_config, "CACHE_DIR", str(tmp_path))
    path = kernel_cache.jit_state().path
    for name, version, stamp in (("kernels.a-1.py311.nbi", numba.__version__, "not the stamp"),
                                 ("kernels.b-2.py311.nbi", "0.1.0", None)):
        with open(os.path.join(path, name), "wb") as f:
            pickle.dump(version, f)
            f.write(pickle.dumps((stamp, {"sig": "data"})))
    with open(os.path.join(path, "kernels.c-3.py311.nbi"), "wb") as f:
        f.write(b"\x00garbage")
    assert kernel_cache.jit_state().fresh == 0


@pytest.mark.parametrize("cold", [False, True])
def test_the_demo_waits_as_long_as_a_start_can_take(tmp_path, monkeypatch, cold):
    from tecdard.tools import demo
    if cold:
        monkeypatch.setattr(numba_config, "CACHE_DIR", str(tmp_path))
        monkeypatch.setattr(build, "aot_problem", lambda: "not built")
    budget, why = demo.startup_budget_s()
    assert budget == (demo.COLD_START_BUDGET_S if cold else demo.WARM_START_BUDGET_S)
    assert ("compiles" in why) == cold


def test_warm_says_compiled_when_it_compiled_and_loaded_when_it_loaded(monkeypatch, capsys, no_build):
    """It once said "loaded in 41 s" after a cold compile: the word comes from the state before. Where
    the build fails (no C compiler), that is one line and the JIT's cache is warmed instead."""
    cold = kernel_cache.CacheState(False, "/cache", 0, 26, "kernels.py")
    warm = kernel_cache.CacheState(True, "/cache", 26, 26, "kernels.py")
    monkeypatch.setattr(kernel_cache, "build_aot", lambda: "error: command 'cc' failed: No such file or directory")
    for before, word in ((cold, "compiled in 41.0 s"), (warm, "loaded in 41.0 s")):
        monkeypatch.setattr(kernel_cache, "jit_state", lambda b=before: b)
        monkeypatch.setattr(kernel_cache, "warm_jit", lambda: (warm, 41.0))
        assert kernel_cache.main(None) == 0
        out = capsys.readouterr().out.strip().splitlines()
        assert out[0] == ("the kernels could not be built ahead of time (error: command 'cc' failed: No such file "
                          "or directory): numba's JIT runs them")
        assert out[-2].endswith(word)


def test_warm_builds_them_ahead_of_time(monkeypatch, capsys, no_build):
    built = []
    monkeypatch.setattr(kernel_cache, "build_aot", lambda: built.append(1))
    monkeypatch.setattr(kernel_cache, "warm_jit", lambda: pytest.fail("the JIT is not needed"))
    assert kernel_cache.main(None) == 0 and built == [1]
    assert capsys.readouterr().out.startswith("compiled the estimator's kernels ahead of time in ")


@pytest.mark.slow
def test_warm_builds_without_compiling_the_kernels_with_the_jit_first():
    """`tecdard warm` as the install runs it: the command line does not import the estimator (whose
    kernels, not yet built, would be compiled by numba's JIT before the build: 40 s more)."""
    import subprocess
    import sys
    from tests.conftest import ROOT
    code = ("import sys; from tecdard.control.estimators.kernels import build; "
            "build.aot_problem = lambda: 'not built'; from tecdard.tools import kernel_cache; "
            "kernel_cache.build_aot = lambda: None; from tecdard.cli.main import main; rc = main(['warm']); "
            "print(rc, 'tecdard.control.estimators.kernels.run' in sys.modules, "
            "'tecdard.control.pipeline' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[0].startswith("compiled the estimator's kernels ahead of time in ")
    assert lines[-1] == "0 False False"
