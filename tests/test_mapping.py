"""Tactile mapping: the kernel depth estimator, the map task's state machine, and the map files."""
import concurrent.futures
import csv
import json
import math
import pathlib
import struct
import zlib

import numpy as np
import pytest

from tecdard.control.geometry import rotvec_to_matrix
from tecdard.control.mapping import MapParams, MapRecord, MapTask, kernel_depth, raster_xy
from tecdard.control.planner import CartesianPlanner
from tecdard.control.tasks import ContactView, TickInput
from tecdard.sim.world import BoxScene
from tecdard.api import commands as C
from tecdard.verbs.map.files import MapFiles, MapSettings, colormap, write_map

TICK_S = 0.02
R_TOOL_DOWN = np.diag([1.0, -1.0, -1.0])        # the TCP frame of the Panda's home pose
TIP_TCP = np.array([0.06, 0.0, 0.104])          # a block held 30 deg off the vertical, 12 cm
STIFFNESS_N_M = 3000.0                          # the grasp along the tool, as the simulator's
POINT_TOL_M = 1e-6                              # the fake estimator is exact


class Files:
    """The map's files as MapTask takes them: `write` hands the finished record on (to `on_write`, which
    returns its future), `write_partial` keeps what a run that ended early had."""

    def __init__(self, on_write):
        self.on_write, self.partial = on_write, []

    def write(self, record):
        return self.on_write(record)

    def write_partial(self, task_id, record):
        self.partial.append((task_id, record))


def done_now(result):
    fut = concurrent.futures.Future()
    fut.set_result(result)
    return fut


# -- kernel depth ------------------------------------------------------------------

def test_kernel_depth_is_the_gaussian_weighted_mean_of_the_k_nearest():
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1], [0.1, 0.1], [1.0, 1.0]])
    d = np.array([1.0, 2.0, 3.0, 4.0, 100.0])
    sigma = 0.05
    q = np.array([0.02, 0.03])
    got = kernel_depth(xy, d, q, k=4, sigma=sigma)
    r2 = ((xy[:4] - q) ** 2).sum(axis=1)
    w = np.exp(-r2 / (2 * sigma ** 2))
    assert got == pytest.approx(float(w @ d[:4] / w.sum()), rel=1e-12)      # the far point is not among the 4
    # at a probe point with a narrow kernel the estimate is that probe's depth
    assert kernel_depth(xy, d, xy[1], k=4, sigma=0.005) == pytest.approx(2.0, abs=1e-9)
    # k = 1 is nearest-neighbour; more neighbours than points use them all
    assert kernel_depth(xy, d, np.array([0.95, 0.9]), k=1) == 100.0
    assert np.isfinite(kernel_depth(xy[:2], d[:2], np.zeros(2), k=4))
    assert np.isnan(kernel_depth(np.zeros((0, 2)), np.zeros(0), np.zeros((3, 2)))).all()


def test_kernel_depth_does_not_underflow_far_from_every_probe():
    xy = np.array([[0.0, 0.0], [0.01, 0.0]])
    got = kernel_depth(xy, np.array([1.0, 3.0]), np.array([5.0, 0.0]), k=2, sigma=0.001)
    assert got == pytest.approx(3.0)          # the nearer of the two dominates, no NaN


def test_raster_covers_the_region_rows_along_y():
    q = raster_xy(np.array([0.3, -0.1]), np.array([0.2, 0.1]), 0.01)
    assert q.shape == (10, 20, 2)
    assert q[0, 0].tolist() == pytest.approx([0.305, -0.095])
    assert q[0, 1, 0] > q[0, 0, 0] and q[1, 0, 1] > q[0, 0, 1]


# -- the map task against a fake arm and estimator ------------------------------------

class FakeRig:
    """Planner-driven TCP (the control thread's moves), a rigid tool in a soft grasp over a BoxScene, and
    an estimator that reports the true touch point once an episode runs. `trigger` False: impacts go
    unnoticed. As in the simulator (sim.world.PivotWorld), a touching tip stays pinned and the tool
    turns in the grasp about it, compressing the grasp along the tool; it lifts off 3 mm beyond its
    length and keeps the attitude it had."""

    def __init__(self, scene: BoxScene, p0: np.ndarray, trigger: bool = True):
        self.scene = scene
        self.planner = CartesianPlanner(TICK_S, 0.05, 0.5, 5.0)
        self.planner.reset(p0)
        self.p = p0.copy()
        self.R = R_TOOL_DOWN.copy()
        self.trigger = trigger
        self.t = 0.0
        self.episode = 0
        self.touch = None            # pinned tip while the tool touches
        self.tip_tcp = TIP_TCP.copy()    # the tool in the grasp, TCP frame
        self.p_touch = None
        self.length = float(np.linalg.norm(TIP_TCP))
        self.tracking = False
        self.phases = []
        self.trace = []              # (phase, TCP, R, the tool in the grasp) per tick
        self.lowest_tip = np.inf

    def tip(self) -> np.ndarray:
        return self.p + self.R @ self.tip_tcp

    def force(self) -> np.ndarray:
        if self.touch is None:
            return np.zeros(3)
        r = self.touch - self.p                    # TCP -> pinned tip
        dist = float(np.linalg.norm(r))
        return STIFFNESS_N_M * max(self.length - dist, 0.0) * r / dist

    def run(self, task: MapTask, max_ticks: int = 200000, until=None) -> MapTask:
        for _ in range(max_ticks):
            if until is not None and until(task):
                return task
            self.t += TICK_S
            tip = self.tip()
            self.lowest_tip = min(self.lowest_tip, tip[2])
            if self.touch is None and tip[2] <= self.scene.surface_z(tip[0], tip[1]):
                self.touch = np.array([tip[0], tip[1], self.scene.surface_z(tip[0], tip[1])])
                self.p_touch = self.p + (self.touch - tip)      # the TCP at the instant of impact (the onset's)
                if self.trigger and task.status.phase == "descend":
                    self.tracking = True
            elif self.touch is not None:
                r = self.touch - self.p
                dist = float(np.linalg.norm(r))
                self.tip_tcp = self.R.T @ (r / dist * self.length)      # the tool turns about its tip
                if dist > self.length + 0.003:
                    self.touch = None                                 # lifted off, keeping that attitude
            view = ContactView(tracking=self.tracking, p=self.touch, std=np.full(3, 1e-3), onset_p_tcp=self.p_touch,
                               axis=np.array([0.0, 1.0, 0.0]), in_plane_std=1e-3) if self.tracking \
                else ContactView(tracking=False)
            motion = task.step(TickInput(self.t, self.p.copy(), self.R.copy(), view, self.planner.at_rest,
                                         self.planner.position, self.force()))
            if not self.phases or self.phases[-1] != task.status.phase:
                self.phases.append(task.status.phase)
            self.trace.append((task.status.phase, self.p.copy(), self.R.copy(), self.tip_tcp.copy()))
            if task.episode != self.episode:
                self.episode = task.episode
                self.tracking = bool(task.commanded_onset and self.touch is not None)
                task.commanded_onset = False
            if task.status.state != "running":
                return task
            if motion is None:
                self.p, _ = self.planner.brake()
                continue
            self.planner.set_speed(motion.max_speed or task.speed)
            self.p, _ = self.planner.step(motion.p, motion.v, motion.min_duration_s)
            self.R = motion.R
        raise AssertionError(f"map task still running in phase {task.status.phase}")


def map_params(**kw) -> MapParams:
    base = dict(origin_xy=np.array([0.32, -0.04]), size_xy=np.array([0.08, 0.08]), grid=(2, 2), depth=0.06,
                orientations=2, speed=0.01, travel_speed=0.035, tool_tip_tcp=TIP_TCP)
    base.update(kw)
    return MapParams(**base)


SCENE = BoxScene(0.33, [(0.33, -0.05, 0.40, 0.0, 0.35)])
P0 = np.array([0.307, 0.0, 0.487])


def test_map_probes_every_grid_point_in_two_orientations_and_hands_the_record_to_the_writer():
    records = []
    task = MapTask("map-1", map_params(), Files(lambda rec: records.append(rec) or done_now({"path": "x"})))
    progress = []
    rig = FakeRig(SCENE, P0)
    orig_step = task.step

    def step(inp):
        m = orig_step(inp)
        progress.append(task.status.progress)
        return m
    task.step = step
    rig.run(task)
    assert task.status.state == "done", task.status.error
    assert task.status.result == {"path": "x"}
    assert np.all(np.diff(progress) >= -1e-12) and progress[-1] == 1.0
    for stage in ("travel", "descend", "settle", "probe", "retract", "lift", "turn", "write"):
        assert stage in rig.phases
    (rec,) = records
    assert isinstance(rec, MapRecord) and len(rec.points) == 8 and rec.yaw_rad == [0.0, math.pi / 2]
    grid = task.grid
    for pt in rec.points:
        assert pt.valid, pt
        # the tool tip was aimed at the grid point, and the fake estimator reports where it touched
        assert np.linalg.norm(pt.p[:2] - grid[pt.row, pt.col]) < 2e-3
        assert pt.p[2] == pytest.approx(SCENE.surface_z(*pt.p[:2]), abs=POINT_TOL_M)
        assert pt.max_force_n < 5.0
    # the second pass turned the tool 90 deg about world z
    assert np.allclose(rig.R, rotvec_to_matrix(np.array([0, 0, math.pi / 2])) @ R_TOOL_DOWN, atol=1e-9)
    assert {(pt.row, pt.col) for pt in rec.points if pt.pass_index == 1} == {(0, 0), (0, 1), (1, 0), (1, 1)}


def test_each_lift_pulls_the_tool_out_along_its_axis_before_rising():
    """Lifted straight up with its tip pinned, a tool levers in a soft grasp; pulled out along its own
    axis it leaves the surface as it is. Every lift goes release_distance away from the tip along the
    tool, then straight up to the travel height."""
    task = MapTask("map-1", map_params(release_distance=0.008), Files(lambda rec: done_now({})))
    rig = FakeRig(SCENE, P0)
    rig.run(task)
    assert task.status.state == "done", task.status.error
    phases = [ph for ph, *_ in rig.trace]
    starts = [i for i in range(1, len(phases)) if phases[i] == "lift" and phases[i - 1] != "lift"]
    assert len(starts) == 8
    for i0 in starts:
        i1 = next(i for i in range(i0, len(phases)) if phases[i] != "lift")
        path = np.array([p for _, p, *_ in rig.trace[i0 - 1:i1]])
        out = path - path[0]
        k = int(np.argmax(np.linalg.norm(out, axis=1) >= 0.008 - 1e-4))
        _, _, R, tip = rig.trace[i0]
        tool = R @ tip / np.linalg.norm(tip)                           # TCP -> tip, world
        assert out[k] @ -tool / np.linalg.norm(out[k]) > np.cos(np.radians(1.0))    # away from the tip
        assert np.linalg.norm(path[k:, :2] - path[k, :2], axis=1).max() < 5e-4      # then straight up
        assert path[-1, 2] == pytest.approx(P0[2], abs=1e-3)


def test_the_tool_model_follows_the_tool_turning_in_the_grasp():
    """The arm brakes after each touch with the tip pinned, so the tool turns in the soft grasp; the model
    turns with it (from the TCP's motion about the touched point) and takes each probe's reach, not the
    direction the probe reports. After every point of both passes it still points where the tool does."""
    task = MapTask("map-5", map_params(), Files(lambda rec: done_now({})))
    rig = FakeRig(SCENE, P0)
    rig.run(task)
    assert task.status.state == "done", task.status.error
    turned = np.degrees(np.arccos(rig.tip_tcp @ TIP_TCP / (np.linalg.norm(rig.tip_tcp) * np.linalg.norm(TIP_TCP))))
    assert turned > 0.3                                      # the tool did turn in the grasp
    off = np.degrees(np.arccos(task.tip_tcp @ rig.tip_tcp / (np.linalg.norm(task.tip_tcp) * rig.length)))
    assert off < 0.1
    assert abs(np.linalg.norm(task.tip_tcp) - rig.length) < 0.002      # the reach, less the grasp's compression


def test_a_missed_impact_is_abandoned_on_force_and_the_point_marked_invalid():
    records = []
    task = MapTask("map-2", map_params(orientations=1), Files(lambda rec: records.append(rec) or done_now({})))
    rig = FakeRig(SCENE, P0, trigger=False)
    rig.run(task)
    # every point abandoned: the map is written, and it is a failure (issue 33: "map done" with 0 of 4)
    assert task.status.state == "failed" and "none of the 4 points is valid (force 4)" in task.status.error
    (rec,) = records
    assert [pt.reason for pt in rec.points] == ["force"] * 4
    assert not any(pt.valid for pt in rec.points)
    # it stopped pushing soon after 5 N: the tip went at most a few mm into the (rigid) fake surface
    assert rig.lowest_tip > SCENE.floor_z - 0.004
    assert "probe" not in rig.phases


def test_nothing_within_depth_is_no_contact():
    records = []
    task = MapTask("map-3", map_params(orientations=1, grid=(1, 2), depth=0.02),
                   Files(lambda rec: records.append(rec) or done_now({})))
    FakeRig(SCENE, P0).run(task)
    assert [pt.reason for pt in records[0].points] == ["no_contact", "no_contact"]


def test_a_failing_writer_fails_the_task():
    def writer(rec):
        fut = concurrent.futures.Future()
        fut.set_exception(OSError("disk full"))
        return fut
    task = MapTask("map-4", map_params(orientations=1, grid=(1, 1)), Files(writer))
    FakeRig(SCENE, P0).run(task)
    assert task.status.state == "failed" and "disk full" in task.status.error


@pytest.mark.slow
def test_a_stopped_map_still_writes_the_points_probed_so_far(tmp_path):
    from tecdard.robots.model import READY_Q, ArmModel
    from tecdard.control.modes import Mode
    from tecdard.runtime.control_thread import ControlParams, ControlThread
    from tecdard.runtime.messages import LatestValue, Outbox
    files = MapFiles(MapSettings(output_dir=str(tmp_path)))
    ct = ControlThread(ControlParams(), ArmModel("panda"), robot=None, ring=None, contact=LatestValue(),
                       directive=LatestValue(), outbox=Outbox(256), q_home=READY_Q["panda"], robot_name="sim",
                       services={"map": files})
    task = MapTask("map-6", map_params(), files)
    FakeRig(SCENE, P0).run(task, until=lambda t: len(t.points) == 3)
    ct.runner.task, ct.runner.mode = task, Mode.BUSY
    ct.runner.end("failed", error="stopped by command")
    files.shutdown(wait=True)
    for ev in files.announcements():
        ct._event(**ev)
    events = []
    while not ct.outbox.empty():
        kind, *rest = ct.outbox.get_nowait()
        if kind == "event":
            events.append(rest[0])
    (failed,) = [e for e in events if e["kind"] == "task_failed"]
    assert failed["map_pending"] is True and "map_path" not in failed     # announced once complete:
    (written,) = [e for e in events if e["kind"] == "map_written"]
    assert written["map_path"] == str(tmp_path / "map-6") and written["summary"]["points"] == 3
    rows = list(csv.DictReader(open(tmp_path / "map-6" / "points.csv")))
    assert len(rows) == 3 and json.loads((tmp_path / "map-6" / "summary.json").read_text())["passes"] == 1


# -- files ---------------------------------------------------------------------------

def read_png(path) -> np.ndarray:
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, w, h = 8, b"", None, None
    while pos < len(data):
        n, tag = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0] == zlib.crc32(tag + body) & 0xFFFFFFFF
        if tag == b"IHDR":
            w, h = struct.unpack(">II", body[:8])
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + 3 * w)
    assert np.all(raw[:, 0] == 0)
    return raw[:, 1:].reshape(h, w, 3)


@pytest.mark.slow
def test_write_map_writes_the_four_files(tmp_path):
    records = []
    task = MapTask("map-5", map_params(), Files(lambda rec: records.append(rec) or done_now({})))
    FakeRig(SCENE, P0).run(task)
    settings = MapSettings(output_dir=str(tmp_path), resolution_m=0.005, kernel_sigma_m=0.022)
    res = write_map(records[0], settings)
    out = tmp_path / "map-5"
    assert res["path"] == str(out) and set(res["files"]) == {"depth.npy", "points.csv", "summary.json", "depth.png"}
    depth = np.load(out / "depth.npy")
    assert depth.shape == (16, 16) and np.isfinite(depth).all()
    # the box (z 0.35) covers y < 0: the lower half of the map is higher than the upper half
    assert depth[:4].mean() > 0.345 and depth[-4:].mean() < 0.335
    rows = list(csv.DictReader(open(out / "points.csv")))
    assert len(rows) == 8 and {r["valid"] for r in rows} == {"1"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["valid"] == 8 and summary["depth"]["shape"] == [16, 16] and summary["kernel"]["k"] == 4
    assert res["summary"] == summary
    data = (out / "depth.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", data[16:24])
    assert (w, h) == (640, 500)                       # the figure (matplotlib, the viz extra)


@pytest.mark.slow
def test_the_depth_image_has_axes_in_mm_and_a_labelled_colour_bar(tmp_path, monkeypatch):
    """Issue 33: a person reads the map's image: world x and y in mm, the height's colour bar
    labelled, the probes marked. Without matplotlib it is the raw raster with its colour bar."""
    pytest.importorskip("matplotlib", reason="the `viz` extra, which `make test` installs")
    import matplotlib
    from tecdard.verbs.map import files as map_files
    records = []
    task = MapTask("map-6", map_params(), Files(lambda rec: records.append(rec) or done_now({})))
    FakeRig(SCENE, P0).run(task)
    rec = records[0]
    settings = MapSettings(output_dir=str(tmp_path), resolution_m=0.005, kernel_sigma_m=0.022)
    _, height = map_files.fuse(rec, settings)
    svg = tmp_path / "depth.svg"
    with matplotlib.rc_context({"svg.fonttype": "none", "savefig.format": "svg"}):
        import matplotlib.figure
        real = matplotlib.figure.Figure.savefig
        monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                            lambda self, path, **kw: real(self, path, **{**kw, "format": "svg"}))
        assert map_files.draw_depth(svg, height, rec, rec.params)
    text = svg.read_text()
    for label in ("world x, mm", "world y, mm", "surface height, world z, mm", "probe, valid (8)",
                  "tactile depth map map-6: 8 of 8 probes valid"):
        assert label in text, label
    monkeypatch.setattr(map_files, "draw_depth", lambda *a: False)         # no matplotlib: the raw raster
    res = map_files.write_map(rec, settings)
    img = read_png(pathlib.Path(res["files"]["depth.png"]))
    assert img.shape[0] == 16 * 8 and img.shape[1] > 16 * 8


def test_colormap_marks_unknown_cells_grey():
    rgb = colormap(np.array([0.0, 1.0, np.nan]))
    assert rgb[0].tolist() == [68, 1, 84] and rgb[1].tolist() == [253, 231, 37] and rgb[2].tolist() == [200, 200, 200]


# -- commands --------------------------------------------------------------------------

@pytest.mark.parametrize("payload, code, field", [
    ({"grid": [5]}, C.BAD_TYPE, "grid"),
    ({"grid": [5.0, 6]}, C.BAD_TYPE, "grid"),
    ({"grid": [0, 6]}, C.OUT_OF_LIMITS, "grid"),
    ({"grid": [100, 100]}, C.OUT_OF_LIMITS, "grid"),
    ({"orientations": 3}, C.BAD_TYPE, "orientations"),
    ({"orientations": True}, C.BAD_TYPE, "orientations"),
    ({"size": [0.1]}, C.BAD_TYPE, "size"),
    ({"size": [0.1, 5.0]}, C.OUT_OF_LIMITS, "size"),
    ({"origin": [0.1, "a"]}, C.BAD_TYPE, "origin"),
    ({"depth": 2.0}, C.OUT_OF_LIMITS, "depth"),
    ({"spacing": 0.1}, C.UNKNOWN_FIELD, "spacing"),
])
def test_bad_map_commands_are_refused_naming_the_field(payload, code, field):
    with pytest.raises(C.CommandError) as err:
        C.validate("map", payload, C.Limits())
    assert err.value.code == code and err.value.message.startswith(field)


def test_map_defaults_are_the_papers_grid_in_two_orientations():
    f = C.validate("map", {}, C.Limits())
    assert f["grid"] == [5, 6] and f["orientations"] == 2 and f["origin"] is None


def test_maps_go_to_the_state_directory_under_systemd_else_the_users(monkeypatch, tmp_path):
    from tecdard.verbs.map.files import default_output_dir
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/tecdar")
    assert default_output_dir() == "/var/lib/tecdar/maps"
    monkeypatch.delenv("STATE_DIRECTORY")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert default_output_dir() == str(tmp_path / "tecdar" / "maps")
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_output_dir() == str(tmp_path / "home" / ".local" / "state" / "tecdar" / "maps")


def test_a_map_is_written_private_and_complete_or_not_at_all(tmp_path, monkeypatch):
    """Files 0600 in a 0700 directory that appears in one rename; a writer that dies mid-way leaves
    only a hidden partial directory, which the next start removes."""
    import stat
    from tecdard import files
    from tecdard.verbs.map import files as mapfiles
    records = []
    task = MapTask("map-7", map_params(orientations=1, grid=(1, 2), depth=0.02),
                       Files(lambda rec: records.append(rec) or done_now({})))
    FakeRig(SCENE, P0).run(task)
    settings = MapSettings(output_dir=str(tmp_path / "maps"))
    res = mapfiles.write_map(records[0], settings)
    out = tmp_path / "maps" / "map-7"
    assert res["path"] == str(out)
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    assert {stat.S_IMODE(f.stat().st_mode) for f in out.iterdir()} == {0o600}
    # a writer killed after two files: nothing under the task's name
    def dies(*_args):
        raise KeyboardInterrupt
    monkeypatch.setattr(mapfiles, "draw_depth", dies)          # the last file written
    with pytest.raises(KeyboardInterrupt):
        mapfiles.write_map(MapRecord("map-8", records[0].params, records[0].points, records[0].yaw_rad), settings)
    assert not (tmp_path / "maps" / "map-8").exists()
    assert [p.name for p in (tmp_path / "maps").iterdir()] == ["map-7"]      # cleaned on the way out
    (tmp_path / "maps" / (files.PARTIAL_PREFIX + "map-9-xyz")).mkdir()      # as a SIGKILL leaves it
    files.ensure_writable_dir(tmp_path / "maps", "map.output_dir")
    assert [p.name for p in (tmp_path / "maps").iterdir()] == ["map-7"]
