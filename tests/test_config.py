"""Configuration: typed getters, unknown keys, and `tecdard run` refusing bad configs with exit 2."""
import json
import subprocess
import sys

import pytest

from tecdard.config import Config, ConfigError, dump_yaml
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
    with pytest.raises(ConfigError, match=r"^a\.sped: unknown option \(did you mean a\.speed\?\)$"):
        cfg.check_unused()
    cfg = Config({"a": {"speed": 1.0, "banana": 2.0}})
    cfg.section("a").getfloat("speed")
    with pytest.raises(ConfigError, match=r"^a\.banana: unknown option$"):     # nothing close: no guess
        cfg.check_unused()


def run_with(tmp_path, cfg):
    """`tecdard run --config` on a bad config, in this process (the same entry point, without the
    interpreter's start-up per case; test_run_exits_2_... below runs the real command line). A
    bad config never gets as far as starting anything."""
    import contextlib
    import io
    import os
    import types
    from tecdard.cli.main import main
    path = tmp_path / "bad.yaml"
    path.write_text(cfg if isinstance(cfg, str) else dump_yaml(cfg))
    err = io.StringIO()
    umask = os.umask(0o022)              # `run` sets the daemon's own umask: not this process's
    os.umask(umask)
    try:
        with contextlib.redirect_stderr(err):
            code = main(["run", "--config", str(path)])
    finally:
        os.umask(umask)
    return types.SimpleNamespace(returncode=code, stderr=err.getvalue())


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
    ({"zenoh.mode": "router"}, "zenoh.mode"),
    ({"zenoh.mode": "client", "zenoh.connect": ["tcp/127.0.0.1:7447"]}, "zenoh.listen: a Zenoh client listens on nothing"),
    ({"zenoh.mode": "client", "zenoh.listen": ...}, "zenoh.connect: mode client needs a router"),
    ({"zenoh.listen": []}, "zenoh.listen: empty, and nothing in zenoh.connect"),
    ({"ros2": {"enabled": True, "namespace": "lab/arm 1"}}, "ros2.namespace: 'lab/arm 1' is no ROS 2 namespace"),
    ({"ros2": {"enabled": True, "distro": "iron"}}, "ros2.distro"),
    ({"ros2": {"enabled": True, "base_frame": "/world"}}, "ros2.base_frame: '/world': a tf2 frame id"),
    ({"ros2": {"enabled": True, "node_name": "tec-dar"}}, "ros2.node_name: 'tec-dar' is no ROS 2 node name"),
    ({"ros2": {"enabld": True}}, "ros2.enabld: unknown option (did you mean ros2.enabled?)"),
    ({"estimator.ekf": {"sigma_W": 0.1}}, "estimator.ekf.sigma_W: unknown option (did you mean estimator.ekf.sigma_w?)"),
    ({"robot.ros2": {"stale_s": 0.1}}, "robot.ros2: unknown option"),
    ({"robot.tcp_link": "tool0"}, "robot.tcp_link: only with robot.urdf"),
    ({"robot.backend": "ros2", "sim": ..., "imu.source": "serial", "robot.urdf": "/nonexistent/arm.urdf",
      "robot.tcp_link": "tool0"}, "robot.urdf: /nonexistent/arm.urdf: no such file"),
    ({"robot.backend": "ros2", "sim": ..., "imu.source": "sim"}, "imu.source: with robot.backend ros2"),
    ({"robot.backend": "ros2", "sim": ..., "imu.source": "serial", "robot.urdf": str(ROOT / "README.md"),
      "robot.tcp_link": "tool0"}, "robot.urdf: README.md does not parse as URDF"),
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
    from tecdard.sim.world import HeightField, PivotWorld
    from tecdard.runtime.daemon import Daemon
    cfg = sim_config(**{"sim.hinge": ..., "sim.pivot": {"surface": "scene", "scene_seed": 2,
                                                         "tip_in_tcp": [0.0, 0.06, 0.10]}})
    d = Daemon(Config(cfg))
    world = d.backend.spec.build().world              # what the simulation process builds
    assert isinstance(world, PivotWorld)
    assert isinstance(world.params.surface, HeightField)
    assert not world.in_contact()                  # the tool starts above the container


def test_two_worlds_are_refused():
    from tecdard.runtime.daemon import Daemon
    cfg = sim_config(**{"sim.pivot": {"surface": "table"}})
    with pytest.raises(ConfigError, match="sim.pivot: give one world"):
        Daemon(Config(cfg))


def test_a_world_that_cannot_be_built_is_a_config_error():
    """The daemon builds its world once at the home pose before anything starts."""
    from tecdard.runtime.daemon import Daemon
    cfg = sim_config(**{"sim.hinge.point": [0.307, 0.0, 0.48]})      # 7 mm from the home TCP
    with pytest.raises(ConfigError, match="hinge.point: the TCP must be at least 2 cm"):
        Daemon(Config(cfg))


# -- hostile and careless config files (issue 16) ---------------------------------------------
def refused(tmp_path, text: str | bytes) -> str:
    """What `tecdard run` does with this file, in process: the ConfigError's one line."""
    from tecdard.runtime.daemon import Daemon
    path = tmp_path / "bad.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError) as info:
        Daemon(Config.load(path))
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 400, msg
    return msg


def sim_yaml(**overrides) -> str:
    return dump_yaml(sim_config(**overrides))


@pytest.mark.parametrize("make,fragment", [
    (lambda: sim_yaml().encode("utf-16"), "not UTF-8 text (UTF-16?)"),
    (lambda: b"robot:\n  name: \xff\xfe\n", "not UTF-8 text"),
    (lambda: sim_yaml() + "deep: " + "[" * 200 + "]" * 200 + "\n", "nested deeper than"),
    (lambda: sim_yaml() + "deep: " + "{a: " * 60 + "1" + "}" * 60 + "\n", "nested deeper than"),
    (lambda: sim_yaml().replace("seed: 1", "seed: " + "9" * 400), "an integer of 400 digits"),
    (lambda: sim_yaml().replace("seed: 1", "seed: " + "9" * 5000), "an integer of 5000 digits"),
    (lambda: sim_yaml().replace("max_speed: 0.05", "max_speed: " + "9" * 400 + ".0"), "limits.max_speed"),
    (lambda: sim_yaml(**{"zenoh.listen": ["tcp/127.0.0.1:notaport"]}), "zenoh.listen"),
    (lambda: sim_yaml(**{"zenoh.connect": ["}{\"'\n"]}), "zenoh"),
    (lambda: sim_yaml() + "# " + "x" * (1 << 20) + "\n", "larger than 1048576 bytes"),
    (lambda: sim_yaml(**{"robot.name": "x" * 100_000}), "robot.name: 100000 characters, at most 64"),
    (lambda: sim_yaml(**{"robot.name": "bad/name"}), "robot.name"),
    (lambda: "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
             "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nrobot:\n  name: *c\n", "YAML aliases (*a) are not accepted"),
    (lambda: sim_yaml(**{"limits.default_probe_distance": 0.05, "limits.max_probe_distance": 0.02}),
     "limits.default_probe_distance"),
    (lambda: sim_yaml(**{"limits.default_point_radius": 0.05}), "limits.default_point_radius"),
    (lambda: sim_yaml(**{"limits.default_map_depth": 0.5, "limits.max_map_depth": 0.3}), "limits.default_map_depth"),
    (lambda: sim_yaml(**{"limits.default_speed": 0.001}), "limits.default_speed"),
    (lambda: sim_yaml(**{"robot.q_home": [10.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]}),
     "robot.q_home: joint 1 at 10.000 rad is outside its limits"),
    (lambda: sim_yaml(**{"control.workspace_max": [0.2, 0.6, 0.9]}), "the home TCP"),
    (lambda: sim_yaml(**{"robot.tool_offset": [0.0, 0.0, 100.0]}), "robot.tool_offset: 100 m"),
    (lambda: sim_yaml(**{"estimator.eta_table": [[30.0, float("nan")]]}), "estimator.eta_table"),
    (lambda: sim_yaml(**{"estimator.eta_table": [[float("inf"), 2.0]]}), "estimator.eta_table"),
    (lambda: sim_yaml(**{"estimator.onset.band_hz": [200.0, 40.0]}), "estimator.onset.band_hz"),
    (lambda: sim_yaml(**{"control.workspace_min": [-1e9, -0.6, 0.05]}), "control.workspace_min"),
    (lambda: bytes(range(256)) * 10, "not UTF-8"),
    (lambda: "robot: !!python/object/apply:os.system ['true']\n", "could not determine a constructor"),
])
def test_a_hostile_config_is_one_line_of_refusal(tmp_path, make, fragment):
    assert fragment in refused(tmp_path, make())


def test_an_unwritable_map_directory_is_refused_at_start(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert "map.output_dir" in refused(tmp_path, sim_yaml(**{"map.output_dir": str(blocker / "maps")}))


def test_an_alias_bomb_is_refused_in_bounded_time_and_memory(tmp_path):
    """The red team's bomb expanded to 1e9 elements under robot.name and hung at 5.6 GB."""
    import resource
    import time
    levels = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    levels += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    text = "\n".join(levels) + "\nrobot:\n  name: *a8\n"
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    assert "YAML aliases" in refused(tmp_path, text)
    assert time.monotonic() - t0 < 5.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 100_000      # kB: no expansion


@pytest.mark.slow
@pytest.mark.parametrize("make", [
    lambda: sim_yaml().encode("utf-16"),
    lambda: sim_yaml().replace("seed: 1", "seed: " + "9" * 5000),
    lambda: sim_yaml(**{"zenoh.listen": ["garbage"]}),
])
def test_run_exits_2_with_one_line_on_what_used_to_be_a_traceback(tmp_path, make):
    data = make()
    path = tmp_path / "bad.yaml"
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    res = subprocess.run([sys.executable, "-m", "tecdard", "run", "--config", str(path)],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr, res.stderr


def test_an_arm_that_ros2_drives_is_built_from_a_users_urdf_with_its_node():
    """robot.backend ros2 with a URDF: the model's joints are the file's, the ROS 2 node is on (it reads
    the joint states) and the daemon's access control lets the joint states in."""
    from tecdard.robots.model import robots_dir
    from tecdard.runtime.daemon import Daemon
    urdf = robots_dir() / "ur_description" / "urdf" / "ur5_robot.urdf"
    cfg = sim_config(**{"robot.backend": "ros2", "sim": ..., "imu.source": "serial", "imu.serial": {"port": "/dev/null"},
                        "robot.urdf": str(urdf), "robot.tcp_link": "tool0", "robot.q_home": ...,
                        "zenoh.listen": ["tcp/127.0.0.1:0"]})
    daemon = Daemon(Config(cfg))
    assert daemon.model.joint_names == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                                        "wrist_2_joint", "wrist_3_joint"]
    assert daemon.ros2 is not None and daemon.backend.commands_arm is False
    assert daemon.intake.read_only
    rules = {r["id"]: r for r in json.loads(daemon.zenoh_config.get_json("access_control"))["rules"]}
    assert rules["observe"]["key_exprs"] == ["0/joint_states/**"]
