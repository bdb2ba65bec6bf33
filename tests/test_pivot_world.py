"""The pivot world against closed-form geometry: constrained rotation, translational probing, blunt push."""
import numpy as np
import pytest

from tecdard.sim.world import PivotParams, PivotWorld, TableEdge

DT_S = 1e-3
R_DOWN = np.diag([1.0, -1.0, -1.0])          # tool pointing down (TCP z -> world -z)
L = 0.12


def world(tilt_x=0.0):
    return PivotWorld(PivotParams(tip_in_tcp=np.array([0.0, 0.0, L]), surface=TableEdge(0.30, 0.50)),
                      np.array([0.45, 0.0, 0.30 + L + 0.01]), R_DOWN)


def approach(w, p0, v, seconds):
    p = p0.copy()
    impact_t = None
    for k in range(int(seconds / DT_S)):
        p = p + v * DT_S
        if w.step(p, DT_S):
            impact_t = k * DT_S
    return p, impact_t


def test_approach_impacts_at_the_surface_and_pins_the_tip():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, t_imp = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.6)
    assert t_imp == pytest.approx(0.01 / 0.02, abs=2 * DT_S)
    assert w.contact[2] == pytest.approx(0.30) and w.contact[0] == pytest.approx(0.45)


def test_tangential_arc_keeps_the_lever_arm_and_rotates_about_the_contact():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, _ = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)     # just in contact
    c = w.contact.copy()
    r0 = p - c
    rate = 0.02 / np.linalg.norm(r0)
    for k in range(1, 500):
        ang = rate * k * DT_S                       # rotate about +y through c
        Ry = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
        w.step(c + Ry @ r0, DT_S)
    assert np.allclose(w.contact, c)                # the pivot stays fixed
    assert w.L == pytest.approx(L, abs=1e-3)        # no sliding on the arc
    assert w.rate[1] == pytest.approx(rate, rel=1e-3)
    assert np.linalg.norm(w.force) < w.params.slide_force_n


def test_translational_probe_slides_the_tool_and_changes_the_lever_arm():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, _ = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)
    c = w.contact.copy()
    p, _ = approach(w, p, np.array([0.02, 0.0, -0.01]), 0.5)   # pushes down-and-along: the tool slides
    assert np.allclose(w.contact, c)
    assert w.L < L - 1e-3                           # shorter lever arm (slid in the grasp)
    dist = np.linalg.norm(p - c)
    assert w.L == pytest.approx(dist + w.params.slide_force_n / w.params.grasp_stiffness_n_m, rel=1e-6)


def test_blunt_push_gives_force_not_rotation():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, _ = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)
    forces = []
    for k in range(100):                            # keep pushing straight down
        p = p + np.array([0.0, 0.0, -0.02]) * DT_S
        w.step(p, DT_S)
        forces.append(w.force[2])
    assert np.all(np.diff(forces) >= -1e-12) and forces[-1] == pytest.approx(w.params.slide_force_n)
    assert np.linalg.norm(w.rate) < 1e-9


def test_beyond_the_edge_nothing_is_touched_and_pulling_back_lifts_off():
    w = PivotWorld(PivotParams(tip_in_tcp=np.array([0.0, 0.0, L]), surface=TableEdge(0.30, 0.40)),
                   np.array([0.45, 0.0, 0.50]), R_DOWN)
    p, t_imp = approach(w, np.array([0.45, 0.0, 0.50]), np.array([0.0, 0.0, -0.02]), 5.0)
    assert t_imp is None                            # past the edge there is no table
    w2 = world()
    p, _ = approach(w2, np.array([0.45, 0.0, 0.30 + L + 0.01]), np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)
    approach(w2, p, np.array([0.0, 0.0, 0.02]), 0.3)
    assert not w2.in_contact()
    assert np.linalg.norm(w2.rate) < 1e-9                 # lifting off is no rotation spike


def test_mapping_scene_has_the_container_and_objects():
    from tecdard.sim.world import CONTAINER_M, mapping_scene
    scene = mapping_scene(seed=3)
    assert np.allclose(scene.size_xy, CONTAINER_M[:2], atol=scene.cell)
    floor = 0.05
    assert scene.z.min() == pytest.approx(floor)
    assert scene.z.max() == pytest.approx(floor + CONTAINER_M[2])             # the walls
    inner = scene.z[2:-2, 2:-2]
    assert 0.2 < np.mean(inner > floor + 1e-6) < 0.9                           # objects cover part of it
    assert np.array_equal(mapping_scene(seed=3).z, scene.z)                    # seeded
    assert scene.surface_z(0.0, 0.0) == -np.inf


def test_probing_the_scene_pins_the_tip_at_the_surface_height():
    from tecdard.sim.world import mapping_scene
    scene = mapping_scene(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(5):
        x = scene.origin[0] + rng.uniform(0.03, 0.42)
        y = scene.origin[1] + rng.uniform(0.03, 0.32)
        w = PivotWorld(PivotParams(tip_in_tcp=np.array([0.0, 0.0, L]), surface=scene),
                       np.array([x, y, 0.50]), R_DOWN)
        p = np.array([x, y, 0.50])
        for k in range(10000):                     # up to 0.5 m down: deeper than the floor
            p = p + np.array([0.0, 0.0, -0.05]) * DT_S
            if w.step(p, DT_S):
                break
        assert w.in_contact()
        assert w.contact[2] == pytest.approx(scene.surface_z(x, y))


def test_point_contact_tip_stays_fixed_while_the_tcp_circles():
    """The pen case: the tip in place, the TCP on a horizontal circle above it; the tool pivots about the tip."""
    pen = 0.09
    w = PivotWorld(PivotParams(tip_in_tcp=np.array([0.0, 0.0, pen]), surface=TableEdge(0.30, 1.0)),
                   np.array([0.5, 0.0, 0.30 + pen + 0.002]), R_DOWN)
    p, _ = approach(w, np.array([0.5, 0.0, 0.30 + pen + 0.002]), np.array([0.0, 0.0, -0.02]), 0.1 + 2 * DT_S)
    tip = w.contact.copy()
    a = 0.015                                            # circle radius of the TCP
    h = np.sqrt(w.L ** 2 - a ** 2)
    rates = []
    for k in range(1, 1001):                             # one turn in 1 s
        phi = 2 * np.pi * k / 1000
        w.step(tip + np.array([a * np.cos(phi), a * np.sin(phi), h]), DT_S)
        rates.append(w.rate.copy())
    assert np.allclose(w.contact, tip)                   # the tip stays fixed
    assert w.L == pytest.approx(np.hypot(a, h), abs=1e-6)
    rates = np.array(rates[10:])
    # the tool's rate sweeps two axes: a point contact is observable in 3D
    assert np.linalg.matrix_rank(rates.T @ rates, tol=1e-6 * np.abs(rates).max() ** 2 * len(rates)) >= 2


def test_ongoing_approach_hits_the_edge_and_keeps_moving():
    """Moving down and along at constant speed: impact, then the block pivots and slides as the TCP goes on."""
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.005])
    v = np.array([0.015, 0.0, -0.015])
    p, t_imp = approach(w, p0, v, 1.0)
    assert t_imp == pytest.approx(0.005 / 0.015, abs=2 * DT_S)
    assert w.in_contact()
    assert w.rate[1] > 0                                 # pivoting about the edge direction
    assert w.L < L                                       # and sliding in the grasp as it goes on


def test_tilted_eraser_pivots_where_an_upright_one_only_pushes():
    """The paper tilts the eraser 30 deg so a flat top makes it turn; upright, a flat top gives force (5 N abort)."""
    eraser = 0.11
    out = {}
    for name, tilt in (("tilted", np.radians(30.0)), ("upright", 0.0)):
        tip = eraser * np.array([np.sin(tilt), 0.0, np.cos(tilt)])
        p = np.array([0.45, 0.0, 0.30 + eraser * np.cos(tilt) + 0.005])
        w = PivotWorld(PivotParams(tip_in_tcp=tip, surface=TableEdge(0.30, 1.0)), p, R_DOWN)
        peak_rate = 0.0
        for k in range(1000):                            # straight down at 20 mm/s, 15 mm past the touch
            p = p + np.array([0.0, 0.0, -0.02]) * DT_S
            w.step(p, DT_S)
            peak_rate = max(peak_rate, float(np.linalg.norm(w.rate)))
        out[name] = (peak_rate, float(np.linalg.norm(w.force)))
    assert out["tilted"][0] > 0.05                       # it turns: a rotation the trigger and EKF can use
    assert out["upright"][0] < 1e-6                      # no rotation at all
    assert out["upright"][1] > 5.0                       # a force rise past the paper's 5 N abort
