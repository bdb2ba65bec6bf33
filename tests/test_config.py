"""Configuration: typed getters, unknown keys, and `tecdard run` refusing bad configs with exit 2."""
import subprocess
import sys

import pytest
import yaml

from tecdard.config import Config, ConfigError
from tests.conftest import ROOT, sim_config


def test_typed_getters_and_bounds():
    cfg = Config({"a": {"x": 1.5, "n": 3, "flag": True, "v": [0, 0, 2], "name": "panda"}})
    a = cfg.section("a")
    assert a.getfloat("x", minval=0) == 1.5
    assert a.getint("n") == 3
    assert a.getbool("flag") is True
    assert a.getvec3("v", unit=True) == [0.0, 0.0, 1.0]
    assert a.getstr("name", choices=("panda", "ur5")) == "panda"
    assert a.getfloat("missing", 7.0) == 7.0
    cfg.check_unused()


@pytest.mark.parametrize("data,call,fragment", [
    ({"x": "fast"}, lambda s: s.getfloat("x"), "a.x: expected a finite number"),
    ({"x": -1.0}, lambda s: s.getfloat("x", minval=0.0), "a.x: -1.0 is below the minimum"),
    ({"x": True}, lambda s: s.getint("x"), "a.x: expected an integer"),
    ({"x": [1, 2]}, lambda s: s.getvec3("x"), "a.x: expected 3 numbers"),
    ({"x": [0, 0, 0.5, 0.5]}, lambda s: s.getquat("x"), "a.x: quaternion"),
    ({}, lambda s: s.getfloat("x"), "a.x: missing required option"),
])
def test_errors_name_the_key(data, call, fragment):
    with pytest.raises(ConfigError, match=fragment):
        call(Config({"a": data}).section("a"))


def test_unknown_key_is_rejected():
    cfg = Config({"a": {"speed": 1.0, "sped": 2.0}})
    cfg.section("a").getfloat("speed")
    with pytest.raises(ConfigError, match=r"^a\.sped: unknown option$"):
        cfg.check_unused()


def run_with(tmp_path, cfg) -> subprocess.CompletedProcess:
    path = tmp_path / "bad.yaml"
    path.write_text(cfg if isinstance(cfg, str) else yaml.safe_dump(cfg))
    return subprocess.run([sys.executable, "-m", "tecdard", "run", "--config", str(path)],
                          capture_output=True, text=True, timeout=60, cwd=ROOT)


@pytest.mark.parametrize("overrides,key", [
    ({"control.tick_ms": 20}, "control.tick_ms: unknown option"),
    ({"limits.max_speed": "fast"}, "limits.max_speed: expected a finite number"),
    ({"robot.model": "robbie"}, "robot.model: unknown arm 'robbie'"),
    ({"estimator.onset.accel_threshold": -1}, "estimator.onset.accel_threshold"),
    ({"robot.q_home": [0, 0, 0]}, "robot.q_home: expected 7 numbers"),
    ({"map.kernel_k": 0}, "map.kernel_k"),
    ({"map.kernel_sigma": 0.02}, "map.kernel_sigma: unknown option"),
    ({"sim.hinge": ..., "sim.pivot": {"surface": "boxes", "floor_z": 0.3, "boxes": [[0.1, 0.1, 0.0, 0.2, 0.4]]}},
     "sim.pivot.boxes: a box needs x0 < x1"),
])
def test_run_refuses_bad_config_with_one_line(tmp_path, overrides, key):
    res = run_with(tmp_path, sim_config(**overrides))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert key in lines[0]


def test_run_refuses_missing_file_and_bad_yaml(tmp_path):
    res = subprocess.run([sys.executable, "-m", "tecdard", "run", "--config", str(tmp_path / "nope.yaml")],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2 and "no such config file" in res.stderr
    res = run_with(tmp_path, "robot: [unclosed\n")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1


def test_daemon_builds_the_mapping_scene_world():
    from robots.world import HeightField, PivotWorld
    from tecdard.daemon import Daemon
    cfg = sim_config(**{"sim.hinge": ..., "sim.pivot": {"surface": "scene", "scene_seed": 2,
                                                         "tip_in_tcp": [0.0, 0.06, 0.10]}})
    d = Daemon(Config(cfg))
    world = d.sim_spec.build().world               # what the simulation process builds
    assert isinstance(world, PivotWorld)
    assert isinstance(world.p.surface, HeightField)
    assert not world.in_contact()                  # the tool starts above the container


def test_two_worlds_are_refused():
    from tecdard.daemon import Daemon
    cfg = sim_config(**{"sim.pivot": {"surface": "table"}})
    with pytest.raises(ConfigError, match="sim.pivot: give one world"):
        Daemon(Config(cfg))


def test_a_world_that_cannot_be_built_is_a_config_error():
    """The daemon builds its world once at the home pose before anything starts."""
    from tecdard.daemon import Daemon
    cfg = sim_config(**{"sim.hinge.point": [0.307, 0.0, 0.48]})      # 7 mm from the home TCP
    with pytest.raises(ConfigError, match="hinge.point: the TCP must be at least 2 cm"):
        Daemon(Config(cfg))
