"""The soft fingertip (hardware/fingertip/): every part of the OpenSCAD design renders to a closed, consistently
oriented mesh; the carrier sits in the pad under `imu_depth` of silicone; a design that leaves no silicone behind
the carrier is refused with OpenSCAD's assertion."""
import importlib.util
import shutil

import numpy as np
import pytest

from tests.conftest import ROOT

spec = importlib.util.spec_from_file_location("fingertip_render", ROOT / "hardware" / "fingertip" / "render.py")
render = importlib.util.module_from_spec(spec)
spec.loader.exec_module(render)

needs_openscad = pytest.mark.skipif(shutil.which("openscad") is None,
                                    reason="openscad is not installed (CI's .ci/run installs it: apt install openscad)")


def cube_triangles(flip=False, drop=0):
    """A unit cube's 12 outward triangles (optionally all flipped, or some dropped)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    faces = [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (1, 2, 6), (1, 6, 5),
             (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7)]
    tris = np.array([[v[i] for i in (f[::-1] if flip else f)] for f in faces])
    return tris[drop:]


def test_the_mesh_check_finds_holes_seams_and_inside_out_meshes():
    assert render.mesh_problems(cube_triangles()) == []
    assert render.volume_mm3(cube_triangles()) == pytest.approx(1.0)
    assert any("hole" in p for p in render.mesh_problems(cube_triangles(drop=1)))
    assert any("inside out" in p for p in render.mesh_problems(cube_triangles(flip=True)))
    mixed = cube_triangles()
    mixed[0] = mixed[0][::-1]
    assert any("same way" in p for p in render.mesh_problems(mixed))


@pytest.mark.slow
@needs_openscad
def test_every_part_renders_closed_and_the_carrier_is_cast_in(tmp_path):
    meshes = {}
    for part in render.PARTS:
        tris = render.read_stl(render.render(part, tmp_path))
        assert render.mesh_problems(tris) == [], part
        assert render.volume_mm3(tris) > 0
        meshes[part] = tris.reshape(-1, 3)
    pad_lo, pad_hi = meshes["pad"].min(0), meshes["pad"].max(0)
    car_lo, car_hi = meshes["carrier"].min(0), meshes["carrier"].max(0)
    np.testing.assert_allclose(pad_hi - pad_lo, [15.0, 10.0, 6.0], atol=1e-6)     # the paper's 15 x 10 mm face
    assert car_lo[2] == pytest.approx(2.0) and np.all(car_lo[:2] > pad_lo[:2] + 1) and np.all(car_hi < pad_hi)
    # the backing's boss fits the mould's cavity with its clearance, and its plate lands on the rim
    for backing in ("backing_franka", "backing_robotiq"):
        assert meshes[backing][:, 2].min() == pytest.approx(6.0) and meshes[backing][:, 2].max() == pytest.approx(12.0)
    assert meshes["mould"][:, 2].max() > 9.0 and meshes["mould"][:, 2].min() == pytest.approx(-2.0)
    png = tmp_path / "fingertip.png"
    render.draw({p: tmp_path / f"{p}.stl" for p in render.PARTS}, png)
    assert png.stat().st_size > 10_000


@pytest.mark.slow
@needs_openscad
def test_a_bonded_backing_has_no_screw_holes_and_stays_closed(tmp_path):
    screwed = render.read_stl(render.render("backing_franka", tmp_path))
    (tmp_path / "b").mkdir()
    bonded = render.read_stl(render.render("backing_franka", tmp_path / "b", mount='"bonded"'))
    assert render.mesh_problems(bonded) == []
    assert render.volume_mm3(bonded) > render.volume_mm3(screwed) + 40    # two M3 holes and counterbores filled


@pytest.mark.slow
@needs_openscad
def test_a_pad_too_thin_for_its_carrier_is_refused(tmp_path):
    with pytest.raises(RuntimeError, match="1 mm of silicone behind it"):
        render.render("pad", tmp_path, pad_t=3)
