"""Issue 17: the estimator's compiled kernels are cached at install, and a start that must compile says so."""
import logging
import os
import pickle

import numba
import pytest
from numba.core import config as numba_config

from tecdard.tools import kernel_cache


def test_the_installed_cache_is_warm():
    """`make install` ran `tecdard warm`: every kernel of control/estimators/kernels/ loads from the cache."""
    state = kernel_cache.state()
    assert state.expected >= 20 and state.warm and state.fresh == state.expected, state
    assert "cached in" in state.describe()


def test_an_empty_cache_is_cold_and_the_start_says_so(tmp_path, monkeypatch, caplog):
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
    path = kernel_cache.state().path
    for name, version, stamp in (("kernels.a-1.py311.nbi", numba.__version__, "not the stamp"),
                                 ("kernels.b-2.py311.nbi", "0.1.0", None)):
        with open(os.path.join(path, name), "wb") as f:
            pickle.dump(version, f)
            f.write(pickle.dumps((stamp, {"sig": "data"})))
    with open(os.path.join(path, "kernels.c-3.py311.nbi"), "wb") as f:
        f.write(b"\x00garbage")
    assert kernel_cache.state().fresh == 0


@pytest.mark.parametrize("cold", [False, True])
def test_the_demo_waits_as_long_as_a_start_can_take(tmp_path, monkeypatch, cold):
    from tecdard.tools import demo
    if cold:
        monkeypatch.setattr(numba_config, "CACHE_DIR", str(tmp_path))
    budget, why = demo.startup_budget_s()
    assert budget == (demo.COLD_START_BUDGET_S if cold else demo.WARM_START_BUDGET_S)
    assert ("compiles" in why) == cold


def test_warm_says_compiled_when_it_compiled_and_loaded_when_it_loaded(monkeypatch, capsys):
    """It once said "loaded in 41 s" after a cold compile: the word comes from the state before."""
    cold = kernel_cache.CacheState(False, "/cache", 0, 26, "kernels.py")
    warm = kernel_cache.CacheState(True, "/cache", 26, 26, "kernels.py")
    for before, word in ((cold, "compiled in 41.0 s"), (warm, "loaded in 41.0 s")):
        monkeypatch.setattr(kernel_cache, "state", lambda b=before: b)
        monkeypatch.setattr(kernel_cache, "warm", lambda: (warm, 41.0))
        assert kernel_cache.main(None) == 0
        assert capsys.readouterr().out.strip().endswith(word)
