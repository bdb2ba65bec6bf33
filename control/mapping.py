"""Tactile mapping (Experiment C of the paper): the grid-probing task and the kernel depth estimator."""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from tecdard.control.geometry import matrix_to_rotvec, rotvec_to_matrix, unit
from tecdard.control.tasks import ContactView, Motion, Task, TickInput

Z_UP = np.array([0.0, 0.0, 1.0])
ARRIVE_TOL_M = 5e-4           # a travel/lift/retract target counts as reached within this
TURN_TOL_RAD = math.radians(0.5)
TURN_RATE_RAD_S = 0.5         # peak yaw rate of the tool turn between passes
TOOL_MODEL_STD_M = 0.005     # one-sigma of the tool model's tip along a probe's rotation axis
TIP_UPDATE_MAX_M = 0.02       # a probe refines the tool model only when it lands this close to it
TRAVEL_SLACK_S = 5.0          # travel phases may take this much longer than their nominal duration


@dataclass
class MapParams:
    """Everything a map run needs, in SI units and the world frame."""
    origin_xy: np.ndarray                 # corner of the region, m
    size_xy: np.ndarray                   # extent of the region along +x and +y, m
    grid: tuple[int, int]                 # (rows along +y, cols along +x)
    depth: float                          # the deepest a probe descends below the start height, m
    orientations: int = 2                 # 1, or 2: a second pass with the tool turned 90 deg about world z
    speed: float = 0.01                   # descent, probe and retract speed, m/s
    travel_speed: float = 0.035           # travel, lift and turn moves, m/s per axis
    probe_distance: float = 0.005         # tangential probe length (the paper's at most 5 mm), m
    abort_force_n: float = 5.0            # a point is abandoned above this TCP force, N
    max_point_std_m: float = 0.005        # a point is valid when the in-plane one-sigma is below this, m
    tool_tip_tcp: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.1]))  # nominal, TCP frame, m
    turn_yaw_rad: float = math.pi / 2     # tool turn between the passes, about world z
    release_distance: float = 0.008       # the lift first pulls the tool out along its axis this far, m

    def grid_xy(self) -> np.ndarray:
        """(rows, cols, 2) cell centres of the grid, world x-y, m."""
        rows, cols = self.grid
        xs = self.origin_xy[0] + (np.arange(cols) + 0.5) * self.size_xy[0] / cols
        ys = self.origin_xy[1] + (np.arange(rows) + 0.5) * self.size_xy[1] / rows
        X, Y = np.meshgrid(xs, ys)            # (rows, cols)
        return np.stack([X, Y], axis=-1)


@dataclass
class MapPoint:
    """One probing at one grid location in one pass."""
    pass_index: int
    row: int
    col: int
    grid_xy: np.ndarray                    # where the tool tip was aimed, m
    valid: bool = False
    reason: str = ""                       # why a point is invalid: no_contact | force | unresolved
    p: np.ndarray | None = None            # contact point, world, m (along the rotation axis: from the tool model)
    std: np.ndarray | None = None          # one-sigma per world axis, m
    in_plane_std: float = float("nan")     # the estimator's one-sigma in the plane of rotation, m
    axis: np.ndarray | None = None         # rotation axis of the probe, world
    p_tcp: np.ndarray | None = None        # TCP at the detection, m
    max_force_n: float = 0.0

    def to_row(self) -> dict:
        nan3 = [float("nan")] * 3
        return {"pass": self.pass_index, "row": self.row, "col": self.col,
                "grid_x": float(self.grid_xy[0]), "grid_y": float(self.grid_xy[1]),
                "valid": int(self.valid), "reason": self.reason,
                **dict(zip(("x", "y", "z"), nan3 if self.p is None else self.p.tolist())),
                **dict(zip(("std_x", "std_y", "std_z"), nan3 if self.std is None else self.std.tolist())),
                "in_plane_std": self.in_plane_std,
                **dict(zip(("tcp_x", "tcp_y", "tcp_z"), nan3 if self.p_tcp is None else self.p_tcp.tolist())),
                "max_force_n": self.max_force_n}


@dataclass
class MapRecord:
    """What a finished run hands to the map writer."""
    task_id: str
    params: MapParams
    points: list[MapPoint]
    yaw_rad: list[float]


def kernel_depth(xy: np.ndarray, d: np.ndarray, query: np.ndarray, k: int = 4, sigma: float = 0.022) -> np.ndarray:
    """The paper's kernel-weighted depth estimator (eq. kernel_estimator): at each query point the
    Gaussian-weighted mean of the depths of its k nearest probe points.

    xy (n, 2) probe locations and d (n,) their depths; query (..., 2); sigma, m. NaN where n == 0.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    d = np.asarray(d, dtype=float).reshape(-1)
    q = np.asarray(query, dtype=float)
    flat = q.reshape(-1, 2)
    if len(xy) == 0:
        return np.full(q.shape[:-1], np.nan)
    k = min(k, len(xy))
    d2 = ((flat[:, None, :] - xy[None, :, :]) ** 2).sum(axis=-1)          # (m, n)
    nearest = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(xy) else np.broadcast_to(
        np.arange(len(xy)), (len(flat), len(xy)))
    r2 = np.take_along_axis(d2, nearest, axis=1)
    # exp(-(r2 - r2_min) / 2 s^2): the same weights up to a common factor, without underflow far away
    w = np.exp(-(r2 - r2.min(axis=1, keepdims=True)) / (2.0 * sigma * sigma))
    return ((w * d[nearest]).sum(axis=1) / w.sum(axis=1)).reshape(q.shape[:-1])


def raster_xy(origin_xy: np.ndarray, size_xy: np.ndarray, resolution: float) -> np.ndarray:
    """(ny, nx, 2) cell centres covering the region at `resolution` (m); rows along +y, cols along +x."""
    nx = max(1, int(round(size_xy[0] / resolution)))
    ny = max(1, int(round(size_xy[1] / resolution)))
    xs = origin_xy[0] + (np.arange(nx) + 0.5) * size_xy[0] / nx
    ys = origin_xy[1] + (np.arange(ny) + 0.5) * size_xy[1] / ny
    X, Y = np.meshgrid(xs, ys)
    return np.stack([X, Y], axis=-1)


def _yaw(angle: float) -> np.ndarray:
    return rotvec_to_matrix(Z_UP * angle)


class MapTask(Task):
    """The paper's tactile mapping: a grid of probes, in one or two passes of the tool orientation.

    At each grid location, five stages: `descend` from the start height until the onset trigger
    fires (armed only while descending steadily); `settle` to rest; `probe` tangentially for
    `probe_distance` while the estimator, started as the probe starts, localises the contact;
    `retract` back along the probe (the tool turns back in the grasp); `lift`: out along the tool's
    axis by `release_distance`, then vertically; `travel` to the next location. A TCP force above
    `abort_force_n` abandons the point (marked invalid) and lifts. Between passes the tool
    turns by `turn_yaw_rad` about world z (`turn`), which swaps the horizontal axis that a
    probe resolves. When every point is done, `files.write(record)` fuses and writes the map off the
    control thread; it returns a future whose result is the summary for `task_done` (`write`). A run
    that ends early hands the points probed so far to `files.write_partial(task_id, record)`, which
    announces them once written (tecdard.verbs.map.files.MapFiles).

    A probe turns the tool about a horizontal axis, so it resolves the contact in the vertical
    plane of the probe; the coordinate along the axis comes from the tool model. The tool tip is
    aimed at each grid location with the same model: `tool_tip_tcp`, turned with the tool as the arm
    settles after each touch (the tip stays pinned, so the TCP's motion from the onset turns the
    tool about it), its length set to each valid probe's measured reach.
    """

    class Phase(enum.StrEnum):
        TRAVEL = "travel"
        DESCEND = "descend"
        SETTLE = "settle"
        PROBE = "probe"
        RETRACT = "retract"
        LIFT = "lift"
        TURN = "turn"
        WRITE = "write"

    kind = "map"
    trigger_phase = Phase.DESCEND
    touching_phases = (Phase.SETTLE, Phase.PROBE, Phase.RETRACT, Phase.LIFT)
    FORCE_PHASES = (Phase.DESCEND, Phase.SETTLE, Phase.PROBE)   # the force may abandon the point here
    FREE_PHASES = (Phase.TRAVEL, Phase.TURN)                    # a force here fails the map (dragging)

    def __init__(self, task_id: str, params: MapParams, files):
        super().__init__(task_id, np.array([0.0, 0.0, -1.0]), params.speed)
        if params.orientations not in (1, 2):
            raise ValueError("orientations: expected 1 or 2")
        self.m = params
        self.files = files
        self.grid = params.grid_xy()
        self.yaws = [0.0, params.turn_yaw_rad][:params.orientations]
        self.points: list[MapPoint] = []
        self.tip_tcp = np.asarray(params.tool_tip_tcp, dtype=float).copy()   # refined by each valid probe
        self._pass = 0
        self._index = 0                 # point within the pass
        self._R_pass = None
        self._R_from = None
        self._z_travel = 0.0
        self._xy = np.zeros(2)          # TCP x-y for the current point
        self._point: MapPoint | None = None
        self._p_detect = None
        self._p_touch = None            # the TCP when the tip touched (the onset's, else the first tick's)
        self._p_release = None          # where the lift's pull along the tool's axis ends
        self._released = False
        self._t_dir = None
        self._future = None

    # -- geometry ---------------------------------------------------------------
    @property
    def total_points(self) -> int:
        return len(self.yaws) * self.grid.shape[0] * self.grid.shape[1]

    def planned_tcp_xy(self, R_start: np.ndarray) -> np.ndarray:
        """(n, 2) TCP x-y of every probe of every pass, aimed with the nominal tool model."""
        out = []
        for yaw in self.yaws:
            tip_w = _yaw(yaw) @ R_start @ np.asarray(self.m.tool_tip_tcp, dtype=float)
            out.append(self.grid.reshape(-1, 2) - tip_w[:2])
        return np.concatenate(out)

    def ended_early(self) -> dict:
        """A run that was stopped or failed: the points probed so far are written all the same (the
        directory appears complete or not at all, and `map_written` says when it has)."""
        if not self.points or self.status.phase == self.Phase.WRITE:
            return {}
        self.files.write_partial(self.id, MapRecord(self.id, self.m, list(self.points), self.yaws[:self._pass + 1]))
        return {"map_pending": True}

    def _pass_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(e, a): the horizontal probing direction of this pass and the probe's rotation axis."""
        tip_w = self._R_pass @ self.tip_tcp
        h = np.array([tip_w[0], tip_w[1], 0.0])
        if float(np.linalg.norm(h)) < 1e-3:
            h = _yaw(self.yaws[self._pass]) @ np.array([1.0, 0.0, 0.0])   # an upright tool: along the pass
        e = unit(h)
        return e, np.cross(Z_UP, e)

    def _tangent(self) -> np.ndarray:
        """Tangential probe direction: normal to the tool (TCP -> tip) in the probe's vertical plane,
        with the TCP rising (the tool swings towards upright)."""
        e, a = self._pass_axes()
        r = -(self._R_pass @ self.tip_tcp)                    # tip -> TCP
        r = r - float(r @ a) * a
        t = np.cross(a, unit(r, "tool_tip_tcp"))
        if t[2] < -1e-9 or (abs(t[2]) <= 1e-9 and float(t @ e) < 0):
            t = -t
        return unit(t)

    def _aim(self, row: int, col: int) -> np.ndarray:
        """TCP x-y that puts the modelled tool tip over the grid location."""
        tip_w = self._R_pass @ self.tip_tcp
        return self.grid[row, col] - tip_w[:2]

    def _rc(self) -> tuple[int, int]:
        """Row and column of the current point: rows in a serpentine, so travel is short."""
        cols = self.grid.shape[1]
        row, k = divmod(self._index, cols)
        return row, (k if row % 2 == 0 else cols - 1 - k)

    # -- state machine --------------------------------------------------------------
    def _started(self, inp: TickInput) -> None:
        self._z_travel = float(inp.p[2])
        self._R_pass = self.R_hold.copy()
        self._begin_point(inp.t)

    def _begin_point(self, t: float) -> None:
        row, col = self._rc()
        self._point = MapPoint(self._pass, row, col, self.grid[row, col].copy())
        self._xy = self._aim(row, col)
        self._enter(self.Phase.TRAVEL, t)

    def _progress(self, stage: float) -> None:
        """Progress over every point of every pass, `stage` (0..1) into the current one; never backwards
        (the measured descent jitters with the encoders)."""
        done = self._pass * self.grid.shape[0] * self.grid.shape[1] + self._index
        self.status.progress = max(self.status.progress, min(0.99 * (done + stage) / self.total_points, 0.99))

    def step(self, inp: TickInput) -> Motion | None:
        """Task.step; in a phase that touches (descend, settle, probe) the force is checked first, and a
        point abandoned for it holds this tick."""
        if self._running(inp) and self.status.phase in self.FORCE_PHASES and self._aborted(inp):
            return self._hold(inp)
        if self._running(inp) and self.status.phase in self.FREE_PHASES and self._dragging(inp):
            return None
        return super().step(inp)

    def _dragging(self, inp: TickInput) -> bool:
        """In free air (travel, turn) a TCP force above abort_force_n means the tool is caught on
        something or drags what it holds: the map fails (the points so far are written)."""
        if inp.contact_force is None:
            return False
        f = float(np.linalg.norm(inp.contact_force))
        if f <= self.m.abort_force_n:
            return False
        self._fail(f"{self.status.phase}: {f:.1f} N on the TCP in free air (limit {self.m.abort_force_n:g} N, "
                   "map.abort_force_n): the tool is caught on something or drags what it holds")
        return True

    def _aborted(self, inp: TickInput) -> bool:
        """A TCP force above abort_force_n abandons the point (its max force is kept either way)."""
        if inp.contact_force is None:
            return False
        pt = self._point
        f = float(np.linalg.norm(inp.contact_force))
        pt.max_force_n = max(pt.max_force_n, f)
        if f <= self.m.abort_force_n:
            return False
        pt.valid, pt.reason = False, "force"
        self._end_probe(inp, self.Phase.RETRACT if self.status.phase == self.Phase.PROBE else self.Phase.LIFT)
        return True

    def _hold(self, inp: TickInput) -> Motion:
        p = inp.p_ref
        return Motion(p.copy(), np.zeros(3), self._R_pass)

    def _arrived(self, inp: TickInput, target: np.ndarray) -> bool:
        p = inp.p_ref
        return inp.planner_at_rest and float(np.linalg.norm(p - target)) < ARRIVE_TOL_M

    def _move(self, inp: TickInput, target: np.ndarray, speed: float, nominal_s: float) -> Motion | None:
        if self._timed_out(inp.t, nominal_s + TRAVEL_SLACK_S):
            self._fail(f"{self.status.phase}: did not reach {np.round(target, 4).tolist()} in time")
            return None
        return Motion(target, np.zeros(3), self._R_pass, max_speed=speed)

    def _step_travel(self, inp: TickInput) -> Motion | None:
        target = np.array([self._xy[0], self._xy[1], self._z_travel])
        self._progress(0.0)
        if self._arrived(inp, target):
            self.episode += 1                       # a fresh contact episode for this point
            self._enter(self.Phase.DESCEND, inp.t)
            return self._step_descend(inp)
        dist = float(np.linalg.norm(target - inp.p))
        return self._move(inp, target, self.m.travel_speed, dist / self.m.travel_speed)

    def _step_descend(self, inp: TickInput) -> Motion | None:
        target = np.array([self._xy[0], self._xy[1], self._z_travel - self.m.depth])
        s = self._z_travel - float(inp.p[2])
        self._progress(0.5 * min(max(s / self.m.depth, 0.0), 1.0))
        c = inp.contact
        if c.tracking:
            # touched: come to rest first, so that the probe's estimate sees only the tangential motion
            self._point.p_tcp = inp.p.copy()
            self._p_touch = inp.p.copy() if c.onset_p_tcp is None else np.asarray(c.onset_p_tcp, float).copy()
            self.episode += 1
            self._enter(self.Phase.SETTLE, inp.t)
            return None
        if self._arrived(inp, target):
            self._point.reason = "no_contact"
            self._end_probe(inp, self.Phase.LIFT)
            return self._hold(inp)
        return self._move(inp, target, self.m.speed, self.m.depth / self.m.speed)

    def _step_settle(self, inp: TickInput) -> Motion | None:
        """Braking after the touch; at rest, the probe starts and with it the estimator (commanded onset)."""
        if not inp.planner_at_rest:
            if self._timed_out(inp.t, 0.5):
                self._fail("settle: the arm did not come to rest after the touch")
            return None
        self._p_detect = inp.p.copy()
        if self._p_touch is not None:
            # The tip stayed where it touched while the arm braked, so the tool turned in the grasp
            # about it: the model follows that turn (its reach stays).
            tip_w = self._R_pass @ self.tip_tcp
            c_touch = self._p_touch + tip_w
            self.tip_tcp = self._R_pass.T @ (unit(c_touch - self._p_detect) * float(np.linalg.norm(tip_w)))
        self._t_dir = self._tangent()
        self.episode += 1
        self.commanded_onset = True
        self._enter(self.Phase.PROBE, inp.t)
        return self._step_probe(inp)

    def _step_probe(self, inp: TickInput) -> Motion | None:
        target = self._p_detect + self.m.probe_distance * self._t_dir
        s = float((inp.p - self._p_detect) @ self._t_dir)
        self._progress(0.5 + 0.3 * min(max(s / self.m.probe_distance, 0.0), 1.0))
        if self._arrived(inp, target):
            self._record(inp.contact)
            self._end_probe(inp, self.Phase.RETRACT)
            return self._hold(inp)
        return self._move(inp, target, self.m.speed, self.m.probe_distance / self.m.speed)

    def _record(self, c: ContactView) -> None:
        pt = self._point
        if not c.tracking or c.p is None:
            pt.reason = "no_contact"
            return
        e, a = self._pass_axes()
        # along the probe's rotation axis the contact is unobservable: take the tool model's tip
        tip_along = float((self._p_detect + self._R_pass @ self.tip_tcp) @ a)
        p = c.p - float(c.p @ a) * a + tip_along * a
        # world one-sigma: the estimator's across the axis, the tool model's along it
        std = np.sqrt(c.std ** 2 * (1.0 - a * a) + TOOL_MODEL_STD_M ** 2 * a * a)
        pt.p, pt.std, pt.axis, pt.in_plane_std = p, std, a, c.in_plane_std
        if c.in_plane_std > self.m.max_point_std_m:
            pt.reason = "unresolved"
            return
        pt.valid = True
        # The measured reach (TCP to contact) refines the tool model's length for aiming and for the
        # next probes, unless it is far from the model (the tool slid in the grasp, or a poor
        # estimate). Not its direction: a straight probe finds the contact on the normal of the
        # commanded tangent, which the model set, so the direction it reports is the model's own
        # plus the estimate's bias, and fed back each probe that bias would accumulate.
        reach = float(np.linalg.norm(p - self._p_detect))
        tip = self.tip_tcp * (reach / float(np.linalg.norm(self.tip_tcp)))
        if float(np.linalg.norm(tip - self.tip_tcp)) < TIP_UPDATE_MAX_M:
            self.tip_tcp = tip

    def _end_probe(self, inp: TickInput, next_phase: str) -> None:
        """The contact episode of this point is over: the estimate no longer describes what moves."""
        self.episode += 1
        if self._p_detect is None:
            self._p_detect = inp.p.copy()
        self._enter(next_phase, inp.t)

    def _step_retract(self, inp: TickInput) -> Motion | None:
        self._progress(0.85)
        if self._arrived(inp, self._p_detect):
            self._enter(self.Phase.LIFT, inp.t)
            return self._step_lift(inp)
        return self._move(inp, self._p_detect, self.m.speed, self.m.probe_distance / self.m.speed)

    def _step_lift(self, inp: TickInput) -> Motion | None:
        """From where the probe began (or was abandoned): out along the tool's axis, away from the tip,
        by `release_distance`, then straight up to the travel height.

        Pulled out along its axis, the tool leaves the surface without levering in the grasp. Lifted
        straight up with its tip pinned, it would turn in the soft grasp until the grasp's preload let
        go, and keep part of that turn. A straight probe does not see the tool's attitude (the contact
        is found along the normal of the commanded tangent), so the tool model would lag every such
        turn and the probes' estimates with it."""
        self._progress(0.9)
        if self._p_release is None:
            self._p_release = self._p_detect - self.m.release_distance * unit(self._R_pass @ self.tip_tcp)
            self._released = False
        if not self._released:
            if not self._arrived(inp, self._p_release):
                return self._move(inp, self._p_release, self.m.speed, self.m.release_distance / self.m.speed)
            self._released = True
        target = np.array([self._p_release[0], self._p_release[1], self._z_travel])
        if self._arrived(inp, target):
            return self._next_point(inp)
        return self._move(inp, target, self.m.travel_speed, self.m.depth / self.m.travel_speed)

    def _next_point(self, inp: TickInput) -> Motion | None:
        self.points.append(self._point)
        self._point, self._p_detect, self._p_touch, self._p_release = None, None, None, None
        self._index += 1
        if self._index < self.grid.shape[0] * self.grid.shape[1]:
            self._begin_point(inp.t)
            return self._step_travel(inp)
        self._index = 0
        self._pass += 1
        if self._pass < len(self.yaws):
            self._R_from = self._R_pass.copy()
            self._enter(self.Phase.TURN, inp.t)
            self._turn_p = inp.p_ref.copy()
            return self._step_turn(inp)
        self._enter(self.Phase.WRITE, inp.t)
        self.status.progress = 0.99
        self._future = self.files.write(MapRecord(self.id, self.m, list(self.points), list(self.yaws)))
        return None

    def _step_turn(self, inp: TickInput) -> Motion | None:
        """Turn the tool about world z by the pass's yaw, on a smooth profile peaking at TURN_RATE_RAD_S."""
        yaw = self.yaws[self._pass] - self.yaws[self._pass - 1]
        duration = math.pi * abs(yaw) / (2.0 * TURN_RATE_RAD_S)
        tau = min((inp.t - self._phase_t0) / duration, 1.0)
        s = 0.5 * (1.0 - math.cos(math.pi * tau))
        rate = 0.0 if tau >= 1.0 else yaw * math.pi / (2.0 * duration) * math.sin(math.pi * tau)
        R_target = _yaw(yaw * s) @ self._R_from
        self._progress(0.0)
        if tau >= 1.0:
            err = float(np.linalg.norm(matrix_to_rotvec(R_target @ inp.R.T)))
            if err < TURN_TOL_RAD:
                self._R_pass = R_target
                self._begin_point(inp.t)
                return self._step_travel(inp)
            if self._timed_out(inp.t, duration):
                self._fail(f"turn: the tool stayed {math.degrees(err):.1f} deg off the pass orientation")
                return None
        return Motion(self._turn_p, np.zeros(3), R_target, w=Z_UP * rate, max_speed=self.m.travel_speed)

    def _step_write(self, inp: TickInput) -> Motion | None:
        fut = self._future
        if fut is None or not fut.done():
            return None                                   # hold still while the map is written
        exc = fut.exception()
        if exc is not None:
            self._fail(f"map files not written: {exc}")
            return None
        result = fut.result()
        if not any(pt.valid for pt in self.points):
            reasons: dict = {}
            for pt in self.points:
                reasons[pt.reason] = reasons.get(pt.reason, 0) + 1
            said = ", ".join(f"{k} {v}" for k, v in reasons.items()) or "none probed"
            self._fail(f"map: none of the {len(self.points)} points is valid ({said}); "
                       f"what was probed is in {result.get('path')}")
            return None
        self._done(result)
        return None

    STEPS = {Phase.TRAVEL: _step_travel, Phase.DESCEND: _step_descend, Phase.SETTLE: _step_settle,
             Phase.PROBE: _step_probe, Phase.RETRACT: _step_retract, Phase.LIFT: _step_lift, Phase.TURN: _step_turn,
             Phase.WRITE: _step_write}

