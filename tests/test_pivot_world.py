"""The pivot world against closed-form geometry: constrained rotation, translational probing, blunt push."""
import numpy as np
import pytest

from robots.world import PivotParams, PivotWorld, TableEdge

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
    assert np.linalg.norm(w.force) < w.p.slide_force_n


def test_translational_probe_slides_the_tool_and_changes_the_lever_arm():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, _ = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)
    c = w.contact.copy()
    p, _ = approach(w, p, np.array([0.02, 0.0, -0.01]), 0.5)   # pushes down-and-along: the tool slides
    assert np.allclose(w.contact, c)
    assert w.L < L - 1e-3                           # shorter lever arm (slid in the grasp)
    dist = np.linalg.norm(p - c)
    assert w.L == pytest.approx(dist + w.p.slide_force_n / w.p.grasp_stiffness_n_m, rel=1e-6)


def test_blunt_push_gives_force_not_rotation():
    w = world()
    p0 = np.array([0.45, 0.0, 0.30 + L + 0.01])
    p, _ = approach(w, p0, np.array([0.0, 0.0, -0.02]), 0.5 + 2 * DT_S)
    forces = []
    for k in range(100):                            # keep pushing straight down
        p = p + np.array([0.0, 0.0, -0.02]) * DT_S
        w.step(p, DT_S)
        forces.append(w.force[2])
    assert np.all(np.diff(forces) >= -1e-12) and forces[-1] == pytest.approx(w.p.slide_force_n)
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
    from robots.world import CONTAINER_M, mapping_scene
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
    from robots.world import mapping_scene
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
