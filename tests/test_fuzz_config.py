"""Fuzz tier: hypothesis-mutated config files through what `tecdard run` does before it starts
anything (Config.load, then the Daemon's constructor, which reads and checks every option).

Whatever the file, the result is a daemon ready to run or one ConfigError line naming the key:
never another exception, which `tecdard run` would turn into a traceback and exit 1.
"""
import pytest
import yaml
from hypothesis import HealthCheck, given, settings, strategies as st

from tecdard.config import Config, ConfigError, dump_yaml
from tests.conftest import sim_config

MAX_MESSAGE_CHARS = 400
BASE = sim_config()


def leaf_paths(node, prefix=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaf_paths(v, prefix + (k,))
    if prefix:
        yield prefix


PATHS = sorted(set(leaf_paths(BASE)))

hostile_values = st.deferred(lambda: st.one_of(
    st.none(), st.booleans(),
    st.integers(-10**6, 10**6), st.integers(min_value=10**300, max_value=10**310),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20), st.text(min_size=200, max_size=5000),
    st.sampled_from(["tcp/127.0.0.1:7447", "tls/127.0.0.1:1", "garbage", "tcp/[::1]:99999", "", "/dev/null",
                     "panda", "ur5", "sim", "serial", "sim-wire", "ekf", "any", "table", "boxes", "scene"]),
    st.lists(st.floats(-10, 10), max_size=8),
    st.lists(hostile_values, max_size=4),
    st.dictionaries(st.text(max_size=10), hostile_values, max_size=3),
))


def mutated(cfg: dict, path: tuple, value):
    node = cfg
    for key in path[:-1]:
        if not isinstance(node.get(key), dict):
            node[key] = {}
        node = node[key]
    node[path[-1]] = value


def text_of(cfg: dict) -> str:
    return dump_yaml(cfg)


def check(tmp_path, text: str | bytes) -> str:
    """"built" or "refused" (with one short line); any other exception fails the test."""
    from tecdard.runtime.daemon import Daemon
    path = tmp_path / "fuzz.yaml"
    path.write_bytes(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    try:
        Daemon(Config.load(path))
    except ConfigError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and len(msg) <= MAX_MESSAGE_CHARS, msg
        return "refused"
    return "built"


FUZZ = settings(max_examples=150, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                       HealthCheck.data_too_large])


@pytest.mark.slow
@FUZZ
@given(st.lists(st.tuples(st.one_of(st.sampled_from(PATHS),
                                    st.lists(st.text(min_size=1, max_size=12), min_size=1, max_size=3).map(tuple)),
                          hostile_values), min_size=1, max_size=4))
def test_any_mutated_config_is_a_daemon_or_one_line_naming_the_key(tmp_path, changes):
    import copy
    cfg = copy.deepcopy(BASE)
    for path, value in changes:
        mutated(cfg, path, value)
    try:
        text = text_of(cfg)
    except (yaml.YAMLError, ValueError, OverflowError):
        return                                   # not representable as YAML: nothing to feed
    assert check(tmp_path, text) in ("built", "refused")


@pytest.mark.slow
@settings(max_examples=80, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(st.integers(0, len(text_of(BASE))), st.binary(min_size=1, max_size=40), st.integers(0, 60))
def test_any_corrupted_config_file_is_a_daemon_or_one_line(tmp_path, at, junk, cut):
    raw = text_of(BASE).encode()
    assert check(tmp_path, raw[:at] + junk + raw[at + cut:]) in ("built", "refused")


@pytest.mark.slow
@pytest.mark.parametrize("value", [10**400, {"a": [[[]]]}])
def test_every_leaf_takes_a_hostile_value_without_a_traceback(tmp_path, value):
    """Each option in turn, not a random sample: every getter sees each of these once."""
    import copy
    outcomes = []
    for path in PATHS:
        cfg = copy.deepcopy(BASE)
        mutated(cfg, path, value)
        outcomes.append(check(tmp_path, text_of(cfg)))
    assert set(outcomes) <= {"built", "refused"} and outcomes.count("refused") > len(PATHS) // 2
