"""Simulated world: a paper cutter whose handle is hinged to a base that rests on friction."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tecdard.control.geometry import cross3, relative_rotvec, signed_angle, unit
from tecdard.options import option, read_options

GRAVITY_M_S2 = 9.81
BASE_SLIDE_ITERATIONS = 4
MOTION_START_RATE_RAD_S = 0.01   # handle rate that counts as "starts to move"
REST_BEFORE_START_S = 0.2        # handle must have rested this long for a new start event


class MotionStart:
    """Detects an object starting to turn after resting (a breakaway, which rings the fingertip)."""

    def __init__(self):
        self._rest_s = REST_BEFORE_START_S
        self._moving = False

    def update(self, rate_rad_s: float, dt: float) -> bool:
        started = False
        if rate_rad_s > MOTION_START_RATE_RAD_S:
            if not self._moving and self._rest_s >= REST_BEFORE_START_S:
                started = True
            self._moving = True
            self._rest_s = 0.0
        else:
            self._moving = False
            self._rest_s += dt
        return started



@dataclass
class SimTruth:
    """Ground truth that only a simulated world can report (never used by the controller)."""
    hinge_point: np.ndarray
    hinge_axis: np.ndarray
    handle_angle_rad: float
    base_displacement_m: float
    extra: dict = field(default_factory=dict)


@dataclass
class HingeParams:
    """The `sim.hinge` section: the paper cutter, truth the controller never reads."""
    hinge_point: np.ndarray = option(None, "a point of the hinge axis, world (the base at rest)", unit="m",
                                     kind="vec3", key="point", required=True)
    hinge_axis: np.ndarray = option(None, "the hinge's axis, world", kind="unitvec3", key="axis", required=True)
    base_mass_kg: float = option(2.5, "the cutter's base", unit="kg", above=0.0)
    friction_mu: float = option(0.3, "the base's friction on the table: it slides when the horizontal pull "
                                     "exceeds mu m g", above=0.0)
    grasp_stiffness_n_m: float = option(3000.0, "the grasp spring between the TCP and the handle", unit="N/m",
                                        above=0.0)
    table_normal: np.ndarray = option((0.0, 0.0, 1.0), "the table's normal, world", kind="unitvec3")
    breakaway_m_s2: float = option(2.0, "the fingertip's ring when the handle breaks away from rest",
                                   unit="m/s^2", minval=0.0)
    twist_stick_deg: float | None = option(None, "the fingertips twist this far relative to the gripper, then slip; "
                                                 "none: never", unit="deg", kind="optfloat", above=0.0, maxval=180.0)

    def __post_init__(self):
        self.hinge_point = np.asarray(self.hinge_point, dtype=float)
        self.hinge_axis = np.asarray(self.hinge_axis, dtype=float)
        self.table_normal = np.asarray((0.0, 0.0, 1.0) if self.table_normal is None else self.table_normal, float)

    @classmethod
    def from_config(cls, section) -> "HingeParams":
        return read_options(cls, section)


class HingeWorld:
    """The grasped handle turns about a hinge fixed to a movable base.

    The handle is rigid with radius R from the axis (set by the TCP at start).
    The grasp point is the point of the handle circle nearest the TCP; the soft
    grasp is a spring of `grasp_stiffness` between the TCP and that point. The
    spring force reaches the base through the hinge; its horizontal part drags
    the base once it exceeds static friction mu*m*g (quasi-static sliding, the
    vertical part is taken by the table). Following the true arc leaves the
    spring relaxed and the base still; a straight pull stretches it and drags
    the base, as in the paper's failure case.

    The soft fingertips twist with the handle's rotation relative to the gripper
    (about the hinge axis) up to `twist_stick_deg`, then slip (gross slip): the
    fingertip, and so the IMU, then no longer follows the handle. What the IMU
    feels is `object_rate_world()`: the gripper's own rate plus the rate of the
    fingertip's twist, which equals the handle's rate while the grasp sticks.
    """

    def __init__(self, params: HingeParams, p_tcp0: np.ndarray, R_tcp0: np.ndarray | None = None):
        self.params = params
        self.axis = unit(params.hinge_axis, "hinge.axis")
        self.n_table = unit(params.table_normal if params.table_normal is not None else np.array([0, 0, 1.0]),
                            "hinge.table_normal")
        self._base = (0.0, 0.0, 0.0)    # how far the base has slid, world, m
        r = np.asarray(p_tcp0, dtype=float) - params.hinge_point
        r_perp = r - np.dot(r, self.axis) * self.axis
        self.radius = float(np.linalg.norm(r_perp))
        if self.radius < 0.02:
            raise ValueError("hinge.point: the TCP must be at least 2 cm from the hinge axis")
        self.along = float(np.dot(r, self.axis))   # grasp position along the axis, m
        self.e0 = r_perp / self.radius
        self._axis, self._e0, self._n_table = tuple(self.axis.tolist()), tuple(self.e0.tolist()), tuple(self.n_table.tolist())
        self._hinge0 = tuple(np.asarray(params.hinge_point, dtype=float).tolist())
        self.angle = 0.0
        self.rate = 0.0
        self.force = np.zeros(3)
        self._start = MotionStart()
        self._R0 = None if R_tcp0 is None else np.asarray(R_tcp0, dtype=float).tolist()   # gripper at the start
        self._R_prev = self._R0
        self._w_tcp = (0.0, 0.0, 0.0)   # the gripper's own rate, world
        self._twist = 0.0               # the fingertips' twist about the axis, rad
        self._twist_rate = 0.0
        self.slip = 0.0                 # handle rotation the grasp has slipped by, rad

    @property
    def base_offset(self) -> np.ndarray:
        return np.array(self._base)

    @property
    def hinge_now(self) -> np.ndarray:
        return self.params.hinge_point + self.base_offset

    def base_displacement(self) -> float:
        return math.sqrt(sum(b * b for b in self._base))

    def _grasp_deviation(self, p_tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, u = self._deviation(*map(float, p_tcp))
        return np.array(d), np.array(u)

    # The physics steps at 1 kHz, so the per-step geometry is in plain floats: numpy's per-call
    # overhead on 3-vectors made a step of the sliding base cost more than half a millisecond.
    def _deviation(self, px: float, py: float, pz: float) -> tuple[tuple, tuple]:
        """(TCP minus the grasp point on the handle circle, unit radial direction u), world."""
        ax, ay, az = self._axis
        hx, hy, hz = self._hinge0
        bx, by, bz = self._base
        rx, ry, rz = px - hx - bx, py - hy - by, pz - hz - bz
        s = rx * ax + ry * ay + rz * az
        rx, ry, rz = rx - s * ax, ry - s * ay, rz - s * az
        n = max(math.sqrt(rx * rx + ry * ry + rz * rz), 1e-9)
        u = (rx / n, ry / n, rz / n)
        a, rad = self.along, self.radius
        d = (px - (hx + bx + a * ax + rad * u[0]), py - (hy + by + a * ay + rad * u[1]),
             pz - (hz + bz + a * az + rad * u[2]))
        return d, u

    def step(self, p_tcp: np.ndarray, dt: float, R_tcp: np.ndarray | None = None) -> bool:
        """Advance by dt with the TCP at p_tcp; returns True when the handle starts to move."""
        k = self.params.grasp_stiffness_n_m
        f_static = self.params.friction_mu * self.params.base_mass_kg * GRAVITY_M_S2
        nx, ny, nz = self._n_table
        px, py, pz = map(float, p_tcp)
        for _ in range(BASE_SLIDE_ITERATIONS):
            (dx, dy, dz), _ = self._deviation(px, py, pz)
            fn = k * (dx * nx + dy * ny + dz * nz)
            hx, hy, hz = k * dx - fn * nx, k * dy - fn * ny, k * dz - fn * nz
            f_h = math.sqrt(hx * hx + hy * hy + hz * hz)
            if f_h <= f_static:
                break
            # Slide just far enough that the horizontal pull equals kinetic friction.
            c = (f_h - f_static) / k / f_h
            bx, by, bz = self._base
            self._base = (bx + c * hx, by + c * hy, bz + c * hz)
        d, u = self._deviation(px, py, pz)
        self.force = np.array((k * d[0], k * d[1], k * d[2]))
        angle = signed_angle(self._e0, u, self._axis)
        self.rate = (angle - self.angle) / dt
        self.angle = angle
        self._step_grasp_twist(R_tcp, dt)
        return self._start.update(abs(self.rate), dt)

    def _step_grasp_twist(self, R_tcp: np.ndarray | None, dt: float) -> None:
        if R_tcp is None:
            self._w_tcp = (0.0, 0.0, 0.0)
            gripper = 0.0
        else:
            R = R_tcp.tolist()
            if self._R0 is None:
                self._R0 = self._R_prev = R
            w = relative_rotvec(R, self._R_prev)
            self._w_tcp = (w[0] / dt, w[1] / dt, w[2] / dt)
            self._R_prev = R
            g = relative_rotvec(R, self._R0)
            ax, ay, az = self._axis
            gripper = g[0] * ax + g[1] * ay + g[2] * az
        twist = self.angle - gripper - self.slip
        limit = math.radians(self.params.twist_stick_deg) if self.params.twist_stick_deg is not None else math.inf
        if abs(twist) > limit:
            self.slip += twist - math.copysign(limit, twist)
            twist = math.copysign(limit, twist)
        self._twist_rate = (twist - self._twist) / dt
        self._twist = twist

    def object_rate_world(self) -> np.ndarray:
        """The handle's rotation as the fingertip passes it on, world, rad/s: about the hinge axis
        only (a hinge cannot turn any other way; a gripper turning off the axis twists the
        fingertips the other way), at the gripper's rate about the axis plus the fingertips'
        twist, which is the handle's rate while the grasp sticks."""
        ax, ay, az = self._axis
        wx, wy, wz = self._w_tcp
        return (wx * ax + wy * ay + wz * az + self._twist_rate) * self.axis

    def tangent(self, p_tcp: np.ndarray) -> np.ndarray:
        _, u = self._grasp_deviation(p_tcp)
        return cross3(self.axis, u)

    def ring(self, p_tcp: np.ndarray, v_tcp: np.ndarray) -> tuple[np.ndarray, float | None]:
        """(direction, amplitude or None for speed-scaled) of the ring at a start event."""
        return self.tangent(p_tcp), self.params.breakaway_m_s2

    def tcp_force(self) -> np.ndarray:
        """Force of the world on the TCP, N, world frame (the handle pulls back on the grasp)."""
        return -self.force

    def truth(self) -> dict:
        return {"hinge_point": self.hinge_now.copy(), "hinge_axis": self.axis.copy(),
                "handle_angle_rad": self.angle, "base_displacement_m": self.base_displacement(),
                "extra": {"radius_m": self.radius, "hinge_point_initial": self.params.hinge_point.tolist(),
                          "grasp_slip_deg": float(np.degrees(self.slip)),
                          "grasp_twist_deg": float(np.degrees(self._twist))}}


@dataclass
class TableEdge:
    """A table top at height `height` (world z) for x < `edge_x`: its edge is a line along world y."""
    height: float
    edge_x: float

    def surface_z(self, x: float, y: float) -> float:
        return self.height if x <= self.edge_x else -np.inf


class BoxScene:
    """A floor at `floor_z` with boxes on it, each (x0, y0, x1, y1, top_z), world, m: a scene whose
    height field is known exactly (for tests of mapping)."""

    def __init__(self, floor_z: float, boxes: list[tuple[float, float, float, float, float]]):
        self.floor_z = float(floor_z)
        self.boxes = np.array(boxes, dtype=float).reshape(-1, 5)

    def surface_z(self, x: float, y: float) -> float:
        return float(self.surface_z_many(np.array([[x, y]]))[0])

    def surface_z_many(self, xy: np.ndarray) -> np.ndarray:
        """Heights at points (n, 2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        z = np.full(len(xy), self.floor_z)
        for x0, y0, x1, y1, top in self.boxes:
            inside = (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)
            z = np.where(inside, np.maximum(z, top), z)
        return z


def _boxes(section) -> list:
    """sim.pivot.boxes: [[x0, y0, x1, y1, top_z], ...], each with x0 < x1 and y0 < y1."""
    out = []
    for box in section.getrows("boxes", [], width=5, min_rows=0, what="[x0, y0, x1, y1, top_z]"):
        if box[0] >= box[2] or box[1] >= box[3]:
            raise section.error("boxes", f"a box needs x0 < x1 and y0 < y1, got {box}")
        out.append(tuple(float(v) for v in box))
    return out


@dataclass
class PivotParams:
    """The `sim.pivot` section: a held block or pen meets a surface, then pivots about where it touched.
    The surface (`surface`: table, scene or boxes, with its own keys) is built in from_config."""
    tip_in_tcp: np.ndarray = option((0.0, 0.0, 0.12), "the tool's far end (a block's edge, a pen's tip), TCP "
                                                      "frame", unit="m", kind="vec3")
    surface: "TableEdge | HeightField | None" = None   # anything with surface_z(x, y)
    grasp_stiffness_n_m: float = option(3000.0, "along the tool: pushing compresses the grasp", unit="N/m",
                                        above=0.0)
    slide_force_n: float = option(6.0, "the tool slides in the grasp beyond this axial force", unit="N",
                                  above=0.0)
    lift_off_m: float = option(0.003, "the tip leaves the surface when pulled this far back (the grasp's preload)",
                               unit="m", above=0.0)
    breakaway_m_s2: float = option(1.0, "the fingertip's ring when a resting tool starts to turn", unit="m/s^2",
                                   minval=0.0)

    @classmethod
    def from_config(cls, section) -> "PivotParams":
        kind = section.getstr("surface", "table", choices=("table", "scene", "boxes"))
        if kind == "boxes":
            surface = BoxScene(section.getfloat("floor_z"), _boxes(section))
        elif kind == "scene":
            surface = mapping_scene(tuple(section.getfloats("scene_origin_xy", [0.30, -0.175], n=2)),
                                    section.getfloat("scene_floor_z", 0.05),
                                    seed=section.getint("scene_seed", 0, minval=0))
        else:
            surface = TableEdge(section.getfloat("table_height", 0.30), section.getfloat("edge_x", 10.0))
        params = read_options(cls, section, surface=surface)
        params.tip_in_tcp = np.array(params.tip_in_tcp)
        return params


class PivotWorld:
    """A rigid tool held in soft fingertips meets a surface, then pivots about the point it touched.

    Free: the tool moves with the gripper. Contact begins when the tip reaches the surface; the
    tip is then pinned there (static friction) and the tool's direction follows the TCP:
    d = (p_tcp - c) / |p_tcp - c|. The grasp holds the tool at length L from the TCP; pushing
    along the tool compresses the grasp (force k * (L - |p_tcp - c|)) until it slides at
    `slide_force_n`, which is how a translational probe changes the lever arm and how a blunt
    push (no rotation possible) shows up as a force rise. Pulling back lifts the tip off.
    """

    def __init__(self, params: PivotParams, p_tcp0: np.ndarray, R_tcp0: np.ndarray):
        self.params = params
        self.R_tcp0 = np.asarray(R_tcp0, dtype=float)
        self.tip_local = np.asarray(params.tip_in_tcp, dtype=float)
        self.L = float(np.linalg.norm(self.tip_local))
        if self.L < 0.01:
            raise ValueError("pivot.tip_in_tcp: the tool must reach at least 1 cm beyond the TCP")
        self.contact: np.ndarray | None = None
        self.d = None                   # tool direction (TCP -> tip), world
        self.rate = np.zeros(3)         # tool angular velocity, world
        self.force = np.zeros(3)        # force of the surface on the tool (through the grasp), world
        self.contacts = 0
        self._d_prev = None
        self._start = MotionStart()
        self._impact = False

    def tip(self, p_tcp: np.ndarray, R_tcp: np.ndarray) -> np.ndarray:
        return p_tcp + R_tcp @ self.tip_local

    def step(self, p_tcp: np.ndarray, dt: float, R_tcp: np.ndarray | None = None) -> bool:
        """Advance by dt; returns True at the instant of impact."""
        R_tcp = self.R_tcp0 if R_tcp is None else R_tcp
        impact = False
        if self.contact is None:
            tip = self.tip(p_tcp, R_tcp)
            z = self.params.surface.surface_z(tip[0], tip[1])
            d = R_tcp @ self.tip_local / self.L
            if tip[2] <= z:
                # the tip is pinned where it met the surface; it cannot sink in
                self.contact = np.array([tip[0], tip[1], z])
                self.contacts += 1
                impact = True
            else:
                self.rate = np.zeros(3) if self._d_prev is None else cross3(self._d_prev, d) / dt
                self._d_prev, self.d = d, d
                self.force = np.zeros(3)
                return False
        r = p_tcp - self.contact                  # contact -> TCP
        dist = float(np.linalg.norm(r))
        d = -r / max(dist, 1e-9)                  # TCP -> tip
        compression = self.L - dist
        if compression < -self.params.lift_off_m:      # pulled away: the tip lifts off
            # the tool keeps the attitude it had in the soft grasp (it does not snap back)
            self.tip_local = R_tcp.T @ (self.d * self.L) if self.d is not None else self.tip_local
            self.contact = None
            self.force = np.zeros(3)
            self.rate = np.zeros(3)
            return False
        f_axial = self.params.grasp_stiffness_n_m * max(compression, 0.0)
        if f_axial > self.params.slide_force_n:        # the tool slides in the grasp: a shorter lever arm
            self.L = dist + self.params.slide_force_n / self.params.grasp_stiffness_n_m
            f_axial = self.params.slide_force_n
        self.force = -f_axial * d                 # the surface pushes back along the tool
        self.rate = np.zeros(3) if self._d_prev is None else cross3(self._d_prev, d) / dt
        self._d_prev, self.d = d, d
        started = self._start.update(float(np.linalg.norm(self.rate)), dt)
        self._impact = impact
        return impact or started

    def object_rate_world(self) -> np.ndarray:
        return self.rate

    def in_contact(self) -> bool:
        return self.contact is not None

    def ring(self, p_tcp: np.ndarray, v_tcp: np.ndarray) -> tuple[np.ndarray, float | None]:
        """An impact rings along the motion, scaled by speed; a breakaway rings with its own amplitude."""
        speed = float(np.linalg.norm(v_tcp))
        direction = v_tcp / speed if speed > 1e-9 else np.array([0.0, 0.0, 1.0])
        return direction, (None if self._impact else self.params.breakaway_m_s2)

    def tcp_force(self) -> np.ndarray:
        """Force of the world on the TCP, N, world frame (the surface pushes back through the grasp)."""
        return self.force.copy()

    def truth(self) -> dict:
        c = self.contact if self.contact is not None else np.zeros(3)
        return {"hinge_point": np.array(c), "hinge_axis": np.zeros(3), "handle_angle_rad": 0.0,
                "base_displacement_m": 0.0,
                "extra": {"contact": None if self.contact is None else self.contact.tolist(),
                          "lever_arm_m": self.L, "force_n": self.force.tolist(), "contacts": self.contacts}}


class HeightField:
    """A surface given as heights on an x-y grid (world), for probing scenes; outside it: nothing."""

    def __init__(self, origin_xy, cell_m: float, heights: np.ndarray):
        self.origin = np.asarray(origin_xy, dtype=float)
        self.cell = float(cell_m)
        self.z = np.asarray(heights, dtype=float)        # (nx, ny), world z of the top surface

    @property
    def size_xy(self) -> np.ndarray:
        return np.array(self.z.shape) * self.cell

    def surface_z(self, x: float, y: float) -> float:
        i = int(np.floor((x - self.origin[0]) / self.cell))
        j = int(np.floor((y - self.origin[1]) / self.cell))
        if 0 <= i < self.z.shape[0] and 0 <= j < self.z.shape[1]:
            return float(self.z[i, j])
        return -np.inf

    def surface_z_many(self, xy: np.ndarray) -> np.ndarray:
        """Vectorised surface_z for points (n, 2)."""
        ij = np.floor((np.asarray(xy) - self.origin) / self.cell).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < self.z.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.z.shape[1])
        out = np.full(len(ij), -np.inf)
        out[ok] = self.z[ij[ok, 0], ij[ok, 1]]
        return out


CONTAINER_M = (0.45, 0.35, 0.245)      # inner size of the paper's transparent container: x, y, wall height


def mapping_scene(origin_xy=(0.30, -0.175), floor_z: float = 0.05, cell_m: float = 0.0025,
                  seed: int = 0) -> HeightField:
    """The paper's mapping scene: a 45 x 35 x 24.5 cm container holding boxes, cups and books.

    Heights are world z of the top surface; the container floor is at floor_z and its walls rise
    24.5 cm around it. Objects are placed at random (seeded) without overlapping the walls.
    """
    rng = np.random.default_rng(seed)
    sx, sy, wall = CONTAINER_M
    nx, ny = int(round(sx / cell_m)), int(round(sy / cell_m))
    z = np.full((nx, ny), floor_z)
    xs = (np.arange(nx) + 0.5) * cell_m
    ys = (np.arange(ny) + 0.5) * cell_m
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    # two books lying flat, a box, two cups (rims) and a bowl
    for _ in range(2):
        w, d, h = rng.uniform(0.15, 0.22), rng.uniform(0.10, 0.15), rng.uniform(0.02, 0.04)
        x0, y0 = rng.uniform(0.02, sx - w - 0.02), rng.uniform(0.02, sy - d - 0.02)
        z = np.where((X >= x0) & (X < x0 + w) & (Y >= y0) & (Y < y0 + d), np.maximum(z, floor_z + h), z)
    w, d, h = rng.uniform(0.08, 0.12), rng.uniform(0.06, 0.10), rng.uniform(0.06, 0.12)
    x0, y0 = rng.uniform(0.02, sx - w - 0.02), rng.uniform(0.02, sy - d - 0.02)
    z = np.where((X >= x0) & (X < x0 + w) & (Y >= y0) & (Y < y0 + d), np.maximum(z, floor_z + h), z)
    for _ in range(2):
        r, h = rng.uniform(0.035, 0.045), rng.uniform(0.09, 0.12)
        cx, cy = rng.uniform(r + 0.02, sx - r - 0.02), rng.uniform(r + 0.02, sy - r - 0.02)
        rho = np.hypot(X - cx, Y - cy)
        z = np.where((rho <= r) & (rho >= r - 0.004), np.maximum(z, floor_z + h), z)     # the rim
    # walls (one cell thick) at the border
    z[0, :] = z[-1, :] = floor_z + wall
    z[:, 0] = z[:, -1] = floor_z + wall
    return HeightField(origin_xy, cell_m, z)
