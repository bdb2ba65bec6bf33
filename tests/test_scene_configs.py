"""Issue 50 item 14: the scene configs the docs use are shipped, and each runs its documented command: README's
`map` example failed on configs/sim.yaml (its cutter scene has no container to map). configs/sim-map.yaml is the
paper's mapping container; configs/sim-wire.yaml and configs/sim-firmware.yaml are configs/sim.yaml with the other
two simulated IMU sources. Each differs from configs/sim.yaml only where it says (a copy that drifted would show
the user another daemon than the docs describe)."""
import copy
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT, TEST_ALLOWANCES, TEST_IMU_STALE_S, DaemonProcess
from tests.test_firmware import host_build  # noqa: F401  (the fixture: the host board, built once)

pytestmark = pytest.mark.slow

CONFIGS = ROOT / "configs"
MAP_TIMEOUT_S = 600.0
NEAR_M = 0.003                 # the probe's tip on an edge: the surface within this across counts
SURFACE_TOL_M = 0.005          # a mapped point this close to the container's true surface


def shipped(name: str) -> dict:
    return yaml.safe_load((CONFIGS / name).read_text())


def overrides() -> dict[str, dict]:
    """What each scene config changes of configs/sim.yaml, dotted path -> value (... removes)."""
    tilt_tip = [0.06, 0.0, 0.103923]
    return {
        "sim-wire.yaml": {"imu.source": "sim-wire"},
        "sim-firmware.yaml": {"imu.source": "sim-firmware"},
        "sim-map.yaml": {"robot.q_home": [0.0, -0.7591, 0.0, -2.254, 0.0, 1.4949, 0.785],
                         "control.max_accel": 2.0, "control.max_jerk": 40.0, "control.imu_stale_s": 0.25,
                         "map.tool_tip_tcp": tilt_tip, "map.turn_deg": -90.0, "sim.hinge": ...,
                         "sim.pivot": {"tip_in_tcp": tilt_tip, "surface": "scene", "scene_origin_xy": [0.27, -0.175],
                                       "scene_floor_z": 0.161077, "scene_seed": 1}},
    }


def with_test_allowances(cfg: dict) -> dict:
    """A shipped config with the suite's allowances for a loaded machine (tests/conftest.py: the stale-data
    and divergence stops): these tests judge the documented command's answer, and CI (2026-12-07) stopped
    the map on a 110 ms stall of the simulator's states and the sim-wire demo on a 55 ms IMU gap."""
    return with_overrides(cfg, {**TEST_ALLOWANCES,
                                "control.imu_stale_s": max(cfg["control"]["imu_stale_s"], TEST_IMU_STALE_S)})


def with_overrides(base: dict, changes: dict) -> dict:
    out = copy.deepcopy(base)
    for dotted, value in changes.items():
        node = out
        *path, last = dotted.split(".")
        for key in path:
            node = node[key]
        if value is ...:
            del node[last]
        else:
            node[last] = value
    return out


@pytest.mark.parametrize("name", sorted(overrides()))
def test_a_scene_config_is_sim_yaml_but_for_what_it_says(name):
    assert shipped(name) == with_overrides(shipped("sim.yaml"), overrides()[name])
    assert (CONFIGS / name).read_text().startswith("# tecdard on the simulated Panda")
    assert f"configs/{name}" in (ROOT / "README.md").read_text(), f"README does not name configs/{name}"


@pytest.mark.parametrize("source", ["sim-wire", "sim-firmware"])
def test_the_demo_rotates_on_each_imu_source_config(source, host_build, tmp_path):  # noqa: F811
    """The documented command, `tecdard demo --config configs/<source>.yaml` (the demo listens on a free port),
    on that config with the suite's allowances for a loaded machine."""
    config = tmp_path / f"{source}.yaml"
    config.write_text(yaml.safe_dump(with_test_allowances(shipped(f"{source}.yaml"))))
    res = subprocess.run([sys.executable, "-m", "tecdard", "demo", "--config", str(config)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    err = float(re.search(r"hinge error +([0-9.]+) mm", res.stdout).group(1))
    assert err < 5.0, res.stdout


def test_the_map_scenes_documented_first_look_maps_the_container(tmp_path):
    """configs/sim-map.yaml's own first command (its header), against the daemon on that config: every point valid,
    each within 5 mm of the container's true surface. Its two points lie 12 mm or more from any edge (one on the
    floor, one on a box): a first look at a cup's rim read the rim 4 mm across (114 mm above the floor under the
    tip), which the map's own kernel smooths but one point's check cannot."""
    import csv
    from tecdard.sim.world import mapping_scene
    text = (CONFIGS / "sim-map.yaml").read_text()
    (command,) = re.findall(r"^#   tecdard (map .*?) +# a first look", text, flags=re.M)
    cfg = with_test_allowances(shipped("sim-map.yaml"))
    d = DaemonProcess(tmp_path, cfg)
    try:
        res = subprocess.run([sys.executable, "-m", "tecdard", *command.split(), "--connect", d.endpoint,
                              "--timeout", str(MAP_TIMEOUT_S), "--json"],
                             cwd=ROOT, capture_output=True, text=True, timeout=MAP_TIMEOUT_S + 60)
    finally:
        d.close()
    assert res.returncode == 0, res.stderr[-2000:] + d.log()[-3000:]
    ev = [__import__("json").loads(line) for line in res.stdout.splitlines()][-1]
    summary = ev["result"]["summary"]
    assert summary["valid"] == summary["points"] > 0, summary
    pivot = cfg["sim"]["pivot"]
    scene = mapping_scene(tuple(pivot["scene_origin_xy"]), pivot["scene_floor_z"], seed=pivot["scene_seed"])
    # a probe that lands on an edge (a box's, a cup's rim) reads the top, a millimetre across it the height field is
    # the floor: the nearest true surface within NEAR_M across (benchmarks/mapping.py's measure)
    offsets = [(dx, dy) for dx in np.linspace(-NEAR_M, NEAR_M, 7) for dy in np.linspace(-NEAR_M, NEAR_M, 7)]
    with open(ev["result"]["files"]["points.csv"]) as fh:
        for r in csv.DictReader(fh):
            x, y, z = float(r["x"]), float(r["y"]), float(r["z"])
            err = min(abs(z - scene.surface_z(x + dx, y + dy)) for dx, dy in offsets)
            print(f"sim-map first look: point ({x * 1e3:.0f}, {y * 1e3:.0f}) mm, {err * 1e3:.2f} mm from the surface")
            assert err < SURFACE_TOL_M, r
