"""Whole daemon in simulation, started as a subprocess and driven over Zenoh as a client would."""
import csv
import signal
import time

import numpy as np
import pytest

from tecdard.tools.demo import distance_to_axis
from tests.conftest import sim_config, tcp_now

# the slow tier (`make check` leaves it out): whole-daemon runs
pytestmark = pytest.mark.slow

HINGE_TOL_M = 0.010          # issue 2: hinge estimate within 10 mm of the true axis
ANGLE_TOL_DEG = 2.0
ARC_BASE_MAX_M = 0.002       # following the estimated arc leaves the base (nearly) still
STRAIGHT_BASE_MIN_M = 0.020  # issue 6: the paper's failure case, a straight pull, drags the base more than this
TASK_TIMEOUT_S = 90.0
APPROACH_TOL_M = 0.025
POINT_TOL_M = 0.003          # issue 6; measured 0.2-0.85 mm over 8 runs (pens of 9 and 14 cm)


def rotate_until_it_ends(d, **fields) -> dict:
    """A rotate (30 deg unless given): its task_done or task_failed event."""
    reply = d.client.command("rotate", {"angle_deg": 30.0, **fields})
    assert reply["ok"] is True, reply
    return d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)


def run_rotate(d, **fields):
    ev = rotate_until_it_ends(d, **fields)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-3000:]}"
    return ev["result"]


def assert_arc_opened_the_cutter(res: dict) -> dict:
    """A 30 deg rotate by arc: the hinge found, the angle reached, the base left still; returns the sim truth."""
    sim = res["sim"]
    err = distance_to_axis(np.array(res["hinge"]["p"]), np.array(sim["hinge_point"]), np.array(sim["hinge_axis"]))
    summary = f"hinge error {err * 1e3:.2f} mm, angle {sim['angle_deg']:.2f} deg, base {sim['base_displacement'] * 1e3:.2f} mm"
    assert err < HINGE_TOL_M, summary
    assert abs(sim["angle_deg"] - 30.0) < ANGLE_TOL_DEG, summary
    assert sim["base_displacement"] < ARC_BASE_MAX_M, summary
    return sim


def test_rotate_follows_the_arc_and_the_straight_pull_drags_the_base(make_daemon):
    d = make_daemon()
    res = run_rotate(d)
    sim = assert_arc_opened_the_cutter(res)
    assert all(s > 0 for s in res["hinge"]["std"])
    # the tool turned with the handle: the fingertips stayed within their stick limit (10 deg); they
    # keep the probe phase's 1.9 deg and the 1.9 deg the tool trails by after its turning fades in
    assert sim["grasp_slip_deg"] == 0.0 and abs(sim["grasp_twist_deg"]) < 6.0, sim
    q = np.array(d.client.command("status")["state"]["tcp"]["q"])
    turned = np.degrees(2 * np.arccos(min(abs(float(q @ [1.0, 0.0, 0.0, 0.0])), 1.0)))   # from (1, 0, 0, 0) at home
    # the tool turned as far as the handle, less the twist the fingertips hold
    assert abs(turned - (sim["angle_deg"] - abs(sim["grasp_twist_deg"]))) < 1.0, f"tool turned {turned:.1f} deg"

    # The cutter is now open; a second daemon starts from a closed one for the straight pull. At 45 deg
    # (a 12 cm path at this 15 cm radius; the paper's is 15 cm) the handle end leaves the circle by
    # r (sqrt(1 + theta^2) - 1) = 41 mm, which the base absorbs. (Over the paper's full 15 cm the
    # drag ends in a protective stop on force: benchmarks/daemon.md.) Once the handle has turned the
    # fingertips past their stick limit the grasp slips, the IMU stops following the handle and the
    # estimator's innovations grow to 3-25x their expected size: the divergence stop, which has its
    # own test below, would end the pull before it shows the drag, so it is set out of the way here.
    # The dragged base's friction also loads the grasp towards the 15 N force stop by the pull's end;
    # the pull either completes or ends in that stop, after the drag either way.
    d.terminate()           # one simulated arm at a time: an idle daemon and its simulation cost ~0.5 core
    d2 = make_daemon(**{"control.max_nis_ratio": 1000.0})
    ev = rotate_until_it_ends(d2, strategy="straight", angle_deg=45.0)
    if ev["kind"] == "task_failed":
        stop = next(e for e in d2.client.event_log if e["kind"] == "protective_stop")
        assert stop["cause"] == "force", f"{ev}\n{d2.log()[-3000:]}"
    sim2 = ev["result"]["sim"] if ev["kind"] == "task_done" else ev["sim"]
    assert sim2["base_displacement"] > STRAIGHT_BASE_MIN_M, sim2
    assert abs(sim2["grasp_slip_deg"]) > 1.0, sim2          # held orientation: the grasp slipped


@pytest.mark.parametrize("radius", [0.10, 0.25])
def test_rotate_opens_a_cutter_whose_handle_rises_from_the_hinge(make_daemon, radius):
    """Another hinge pose: the handle rises 20 deg from the hinge to the grasp. Probing along the
    handle's tangent (Algorithm 2 of the paper), the arc leaves the base still."""
    tcp, e = np.array([0.307, 0.0, 0.487]), np.radians(20.0)
    hinge = tcp - radius * np.array([np.cos(e), 0.0, np.sin(e)])
    d = make_daemon(**{"sim.hinge.point": hinge.tolist()})
    assert_arc_opened_the_cutter(run_rotate(d, direction=[-np.sin(e), 0.0, np.cos(e)]))


OFF_TANGENT_TOL_M = 0.005    # issue 21: the hinge within 5 mm probing up to 10 deg off the tangent


@pytest.mark.parametrize("off_deg", [-10.0, 10.0])
def test_rotate_probing_off_the_tangent_still_finds_the_hinge(make_daemon, off_deg):
    """The operator's `direction` 10 deg off the handle's tangent (the hinge is unknown, so is the
    tangent): the grasp absorbs the probe's part along the handle, and the velocities put the
    centre turned 10 deg about the TCP. On the arc the radial admittance keeps the TCP on the
    handle's true circle, and its positions triangulate the hinge (ekf.arc_position_sigma):
    within 5 mm at 15 cm, the base still (measured 1.0-2.6 mm; without them 8-16 mm)."""
    radius = 0.15
    tcp = np.array([0.307, 0.0, 0.487])
    d = make_daemon(**{"sim.hinge.point": (tcp - [radius, 0.0, 0.0]).tolist()})
    off = np.radians(off_deg)
    res = run_rotate(d, direction=[np.sin(off), 0.0, np.cos(off)])     # the tangent is +z, the handle +x
    sim = res["sim"]
    err = distance_to_axis(np.array(res["hinge"]["p"]), np.array(sim["hinge_point"]), np.array(sim["hinge_axis"]))
    assert err < OFF_TANGENT_TOL_M, f"hinge {err * 1e3:.2f} mm"
    assert sim["base_displacement"] < ARC_BASE_MAX_M


def test_second_task_is_busy_and_stop_wins(make_daemon):
    d = make_daemon()
    cli = d.client
    first = cli.command("rotate", {"angle_deg": 30.0})
    assert first["ok"] is True
    second = cli.command("probe", {})
    assert second["ok"] is False and second["error"]["code"] == "busy"
    assert first["task"] in second["error"]["message"]
    time.sleep(0.5)
    stop = cli.command("stop", timeout=10.0)
    assert stop == {"ok": True}
    ev = cli.wait_event(("task_failed",), first["task"], 10.0)
    assert "stopped" in ev["error"]
    state = cli.command("status")["state"]
    assert state["task"] is None
    assert np.linalg.norm(state["tcp"]["v"]) < 0.005
    p0 = np.array(state["tcp"]["p"])
    time.sleep(0.3)
    assert np.linalg.norm(tcp_now(cli) - p0) < 0.0005


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signals_stop_motion_and_exit_cleanly(make_daemon, sig):
    d = make_daemon()
    reply = d.client.command("rotate", {"angle_deg": 30.0})
    assert reply["ok"] is True
    time.sleep(0.5)
    t0 = time.monotonic()
    code = d.terminate(sig, timeout=10.0)
    elapsed = time.monotonic() - t0
    assert code == 0, d.log()[-2000:]
    assert "tecdard stopped" in d.log()
    # nothing left for nanobind to report: the planner's Ruckig objects were freed at the thread's end
    assert "leaked" not in d.log(), d.log()[-2000:]
    print(f"exit after {signal.Signals(sig).name}: {elapsed * 1e3:.0f} ms")


def test_probe_localises_the_hinge(make_daemon):
    d = make_daemon()
    reply = d.client.command("probe", {"distance": 0.005})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", ev
    res = ev["result"]
    assert set(res) >= {"p", "std"}
    sim = res["sim"]
    err = distance_to_axis(np.array(res["p"]), np.array(sim["hinge_point"]), np.array(sim["hinge_axis"]))
    assert err < HINGE_TOL_M
    assert sim["base_displacement"] < ARC_BASE_MAX_M
    kinds = [e["kind"] for e in d.client.event_log]
    assert kinds.index("task_started") < kinds.index("contact_onset") < kinds.index("task_done")


def test_rotate_about_a_table_edge_in_the_pivot_world(make_daemon):
    """The paper's constrained line contact: a held block already on a table edge, turned about it."""
    tool_m = 0.12
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": [0.0, 0.0, tool_m],
                                                       "table_height": 0.487 - tool_m, "edge_x": 0.5}})
    reply = d.client.command("rotate", {"angle_deg": 10.0, "direction": [1.0, 0.0, 0.0]})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-2000:]}"
    res = ev["result"]
    contact = np.array(res["sim"]["contact"])
    assert abs(contact[2] - (0.487 - tool_m)) < 1e-3            # the tip touched the table top
    axis = np.array(res["hinge"]["axis"])
    assert abs(abs(axis[1]) - 1.0) < 0.05                        # turned about the edge direction (y)
    err = distance_to_axis(np.array(res["hinge"]["p"]), contact, np.array([0.0, 1.0, 0.0]))
    assert err < HINGE_TOL_M, f"contact error {err * 1e3:.2f} mm"
    assert abs(res["sim"]["lever_arm_m"] - tool_m) < 1e-3        # no sliding on the arc


def test_force_over_the_limit_is_a_protective_stop(make_daemon):
    """Probing straight down with an upright tool on a table: no rotation, the force rises: stop."""
    tool_m = 0.12
    d = make_daemon(**{"sim.hinge": ..., "control.max_force_n": 3.0,
                       "sim.pivot": {"tip_in_tcp": [0.0, 0.0, tool_m], "table_height": 0.487 - tool_m,
                                     "edge_x": 1.0}})
    reply = d.client.command("probe", {"direction": [0.0, 0.0, -1.0], "distance": 0.01, "speed": 0.01})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_failed", "task_done"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_failed"
    stops = [e for e in d.client.event_log if e["kind"] == "protective_stop"]
    assert stops and stops[0]["cause"] == "force" and stops[0]["force_n"] > 3.0
    assert d.client.command("status")["state"]["mode"] in ("idle", "stopped")


def test_rotation_over_the_limit_is_a_protective_stop(make_daemon):
    d = make_daemon(**{"control.max_rotation_deg": 8.0})
    reply = d.client.command("rotate", {"angle_deg": 20.0})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_failed", "task_done"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_failed"
    stop = next(e for e in d.client.event_log if e["kind"] == "protective_stop")
    assert stop["cause"] == "rotation"
    assert 8.0 < stop["angle_deg"] < 9.0              # caught within a tick of crossing the limit


def test_approach_finds_the_table_during_ongoing_motion_and_stops_at_the_angle(make_daemon):
    """The paper's ongoing case: a block held nearly level comes down onto a table at constant speed,
    hits it, pivots about its far edge while the arm keeps going, and the task stops at 5 deg."""
    tool_m, tilt = 0.12, np.radians(10.0)
    tip_tcp = [float(tool_m * np.cos(tilt)), 0.0, float(tool_m * np.sin(tilt))]   # ahead, a little below the TCP
    tip_z = 0.487 - tool_m * np.sin(tilt)
    table = float(tip_z - 0.012)
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": tip_tcp, "table_height": table,
                                                       "edge_x": 1.0}})
    reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                          "stop_angle_deg": 5.0})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-2000:]}"
    res = ev["result"]
    assert res["angle_deg"] >= 5.0
    assert res["travel"] < 0.08
    contact = np.array(res["sim"]["contact"])
    assert abs(contact[2] - table) < 1e-3
    err = distance_to_axis(np.array(res["p"]), contact, np.array([0.0, 1.0, 0.0]))
    # The paper reports ~11 mm in its ongoing experiment; here the block also slides in the grasp as
    # it turns (about a quarter of the motion by the 5 deg stop), and we measure 17-18 mm.
    assert err < APPROACH_TOL_M, f"contact error {err * 1e3:.1f} mm"
    onset = next(e for e in d.client.event_log if e["kind"] == "contact_onset")
    assert abs(onset["p_tcp"][2] - (0.487 - 0.012)) < 0.003, f"{onset}\n{d.log()[-3000:]}"   # fired at the impact


def test_approach_without_contact_fails_at_max_distance(make_daemon):
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": [0.0, 0.0, 0.12], "table_height": 0.1,
                                                       "edge_x": 0.1}})
    reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.03, "max_distance": 0.03})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_failed" and "max_distance" in ev["error"], f"{ev}\n{d.log()[-4000:]}"
    p = np.array(d.client.command("status")["state"]["tcp"]["p"])
    assert p[2] > 0.487 - 0.03 - 0.002                            # never beyond max_distance


def test_estimator_divergence_is_a_protective_stop(make_daemon):
    """A straight pull turns the handle past the fingertips' stick limit (10 deg); the grasp slips and the
    innovations stop fitting the model: the smoothed NIS ratio reads 25-32, against at most 1.9 (3.9 with
    the other core busy) while following the arc. The product's default limit (10) stops it."""
    d = make_daemon(**{"control.max_nis_ratio": sim_config()["control"]["max_nis_ratio"]})
    reply = d.client.command("rotate", {"angle_deg": 30.0, "strategy": "straight"})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_failed", "task_done"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_failed", ev
    stop = next(e for e in d.client.event_log if e["kind"] == "protective_stop")
    assert stop["cause"] == "divergence" and stop["nis_ratio"] > 10.0
    sim = ev["sim"]
    assert sim["angle_deg"] < 20.0 and sim["base_displacement"] < 5e-3, sim


@pytest.mark.parametrize("tool_m", [0.14, 0.09])
def test_point_localises_a_pen_tip_by_circular_probing(make_daemon, tool_m):
    """The paper's pen, held upright: the tip touches the table, the TCP circles once; all three
    coordinates of the tip. (A pen tilted in the grasp ends about L sin(tilt) off: docs/zenoh-api.md.)"""
    tilt = 0.0
    tip_tcp = [float(tool_m * np.sin(tilt)), 0.0, float(tool_m * np.cos(tilt))]
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": tip_tcp, "table_height": 0.487 - tip_tcp[2],
                                                       "edge_x": 1.0}})
    reply = d.client.command("point", {"radius": 0.01, "speed": 0.02})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-2000:]}"
    res = ev["result"]
    err = np.array(res["p"]) - np.array(res["sim"]["contact"])
    assert np.linalg.norm(err) < POINT_TOL_M, f"tip error {np.round(err * 1e3, 2)} mm"
    assert np.all(np.abs(err) <= 3 * np.array(res["std"]) + 1e-4)      # the one-sigma covers it
    assert abs(res["turns"] - 1.0) < 0.02
    assert abs(res["lever_arm"] - res["sim"]["lever_arm_m"]) < 0.005


MAP_POINT_TOL_M = 0.004      # measured within 1.9 mm in z (24 points); 0-6.3 mm while lifts levered the tool
MAP_SCENE = {"floor_z": 0.33, "boxes": [[0.33, -0.05, 0.40, 0.0, 0.35]]}    # a 2 cm box on a table


def test_map_probes_a_small_grid_in_two_orientations_and_writes_the_depth_map(make_daemon, tmp_path):
    """The paper's tactile mapping on a 2 x 1 grid across a box's edge: a block held 30 deg off the
    vertical probes a table with a box on it, in two tool orientations; every point is valid and the
    map matches the scene."""
    from tecdard.sim.world import BoxScene
    tilt, tool_m = np.radians(30.0), 0.12
    tip_tcp = [float(tool_m * np.sin(tilt)), 0.0, float(tool_m * np.cos(tilt))]
    # The longest daemon test (about 42 s of task: 3-5 s of descent at 1 cm/s a point; at 2 cm/s only
    # 1 of 4 points is valid). Like the mapping bench it tolerates 0.25 s of IMU staleness: a 58 ms
    # stall of the shared 2-core machine stopped it once. The 50 ms stop itself is tested by
    # unplugging the board (tests/test_serial_imu.py).
    d = make_daemon(**{"sim.hinge": ..., "sim.pivot": {"tip_in_tcp": tip_tcp, "surface": "boxes", **MAP_SCENE},
                       "map": {"output_dir": str(tmp_path / "maps"), "tool_tip_tcp": tip_tcp},
                       "control.imu_stale_s": 0.25})
    scene = BoxScene(MAP_SCENE["floor_z"], MAP_SCENE["boxes"])
    reply = d.client.command("map", {"origin": [0.32, -0.04], "size": [0.04, 0.08], "grid": [2, 1], "depth": 0.06,
                                     "orientations": 2, "speed": 0.01})
    assert reply["ok"] is True, reply
    progress, phases, ev = [], set(), None
    deadline = time.monotonic() + 2 * TASK_TIMEOUT_S
    while ev is None and time.monotonic() < deadline:
        try:
            ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], 0.5)
        except Exception:
            pass
        while not d.client.states.empty():
            task = d.client.states.get_nowait()["task"]
            if task is not None:
                progress.append(task["progress"])
                phases.add(task["phase"])
    assert ev is not None and ev["kind"] == "task_done", f"{ev}\n{d.log()[-3000:]}"
    assert {"descend", "probe", "retract", "lift", "travel", "turn"} <= phases
    assert progress and all(b >= a for a, b in zip(progress, progress[1:])), "progress went backwards"
    res = ev["result"]
    summary = res["summary"]
    assert summary["points"] == 4 and summary["valid"] == 4 and summary["passes"] == 2
    with open(res["files"]["points.csv"]) as fh:
        rows = list(csv.DictReader(fh))
    grid = {(0, 0): (0.34, -0.02), (1, 0): (0.34, 0.02)}      # on the box, on the table
    for r in rows:
        p = np.array([float(r["x"]), float(r["y"]), float(r["z"])])
        assert abs(p[2] - scene.surface_z(p[0], p[1])) < MAP_POINT_TOL_M, r
        # the tool tip was aimed at the grid point (from the tool model, refined by each probe)
        assert np.linalg.norm(p[:2] - grid[int(r["row"]), int(r["col"])]) < 0.004, r
    depth = np.load(res["files"]["depth.npy"])
    assert depth.shape == (16, 8) and np.isfinite(depth).all()
    # The fused map at the grid points (raster rows along +y) against the same kernel estimator
    # fed the true heights at the probed x-y: the kernel itself mixes in the table 4 cm from the box's
    # points (3.8 mm at one of them from exact heights), the touch adds no more than its points' error.
    from tecdard.control.mapping import kernel_depth, raster_xy
    from tecdard.verbs.map.files import MapSettings
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    truth_z = np.array([scene.surface_z(x, y) for x, y in xy])
    query = raster_xy(np.array([0.32, -0.04]), np.array([0.04, 0.08]), 0.005)
    ideal = kernel_depth(xy, truth_z, query, MapSettings.kernel_k, MapSettings.kernel_sigma_m)
    for (row, col), (x, y) in grid.items():
        i, j = int((y + 0.04) / 0.005), int((x - 0.32) / 0.005)
        assert abs(depth[i, j] - ideal[i, j]) < MAP_POINT_TOL_M
        assert abs(depth[i, j] - scene.surface_z(x, y)) < 0.0045 + MAP_POINT_TOL_M
    assert open(res["files"]["depth.png"], "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_a_second_rotate_probes_along_the_tangent_the_first_left(make_daemon):
    """Issue 50 item 9: after a rotate the handle has turned, and the default direction (straight up) no longer
    runs along its tangent: a second rotate without --direction failed 3 times in 3 ("estimator innovations
    11x"). The daemon now takes the tangent at the grasp about the hinge the first rotate found, onwards,
    and says so in its reply; the handle ends at the sum of both angles, the hinge found again."""
    d = make_daemon()
    first = run_rotate(d, angle_deg=20.0)
    _wait_at_rest(d)
    reply = d.client.command("rotate", {"angle_deg": 20.0})
    assert reply["ok"] is True, reply
    assert "tangent" in reply["direction_from"] and first["hinge"] is not None, reply
    turned = np.radians(first["sim"]["angle_deg"])      # the handle's true tangent now: +z turned with it
    true_tangent = np.array([-np.sin(turned), 0.0, np.cos(turned)])
    assert float(np.dot(reply["direction"], true_tangent)) > np.cos(np.radians(5.0)), (reply, true_tangent)
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    assert ev["kind"] == "task_done", f"{ev}\n{d.log()[-3000:]}"
    sim = ev["result"]["sim"]
    err = distance_to_axis(np.array(ev["result"]["hinge"]["p"]), np.array(sim["hinge_point"]), np.array(sim["hinge_axis"]))
    print(f"second rotate: hinge {err * 1e3:.2f} mm, handle {sim['angle_deg']:.2f} deg, direction "
          f"{np.degrees(np.arccos(min(1.0, float(np.dot(reply['direction'], true_tangent))))):.2f} deg off the tangent")
    assert err < HINGE_TOL_M, f"hinge {err * 1e3:.2f} mm"
    assert abs(sim["angle_deg"] - 40.0) < 2 * ANGLE_TOL_DEG, sim
    started = next(e for e in d.client.event_log if e["kind"] == "task_started" and e["task"] == reply["task"])
    assert started["params"]["direction"] == reply["direction"] and started["params"]["direction_from"]
    # a direction given is the operator's: no hinge's tangent replaces it
    _wait_at_rest(d)
    given = d.client.command("rotate", {"angle_deg": 5.0, "direction": [0.0, 0.0, 1.0]})
    assert given["ok"] is True and "direction_from" not in given, given
    d.client.command("cancel", {"task": given["task"]})


def _wait_at_rest(d, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while d.client.command("status")["state"]["mode"] == "busy":
        assert time.monotonic() < deadline, d.log()[-2000:]
        time.sleep(0.05)


@pytest.mark.parametrize("rig", [{}, {"scale": 1.0}, {"scale": 1.0, "only": "dither"}])
def test_an_impact_is_decided_at_its_own_sample_while_the_daemon_drives(make_daemon, rig):
    """Issue 48: the daemon's own approach at 20 mm/s onto a table, clean, with every disturbance of a real
    rig at 1x (sim.rig), and with the servo's dither alone: no onset on the way down, and the impact
    decided at its own sample (its control ticks said the arm took no step of its own:
    control.command_track), not after the arm's states or the ring's swing back. Before, with the dither
    the trigger never armed: its 40 Hz turned the fingertip's 5 ms twist mean across the threshold, so
    the task start's settling never ended; it is judged on the twist's 50 ms hold mean now."""
    tool_m, tilt = 0.12, np.radians(10.0)
    tip_tcp = [float(tool_m * np.cos(tilt)), 0.0, float(tool_m * np.sin(tilt))]
    table = float(0.487 - tool_m * np.sin(tilt) - 0.012)
    d = make_daemon(**{"sim.hinge": ..., "sim.rig": rig,
                       "sim.pivot": {"tip_in_tcp": tip_tcp, "table_height": table, "edge_x": 1.0}})
    reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                          "stop_angle_deg": 5.0})
    assert reply["ok"] is True
    ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
    onset = next((e for e in d.client.event_log if e["kind"] == "contact_onset"), None)
    assert onset is not None, f"{ev}\n{d.log()[-3000:]}"
    assert abs(onset["p_tcp"][2] - (0.487 - 0.012)) < 0.003, f"{onset}\n{d.log()[-3000:]}"   # at the impact
    assert onset["trigger"] == "accel" and onset["detected_t"] - onset["t"] <= 0.002, onset
