"""Simulated world: a paper cutter whose handle is hinged to a base that rests on friction."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from control.geometry import signed_angle, unit

GRAVITY_M_S2 = 9.81
BASE_SLIDE_ITERATIONS = 4
MOTION_START_RATE_RAD_S = 0.01   # handle rate that counts as "starts to move"
REST_BEFORE_START_S = 0.2        # handle must have rested this long for a new start event


@dataclass
class HingeParams:
    hinge_point: np.ndarray          # a point of the hinge axis, world, m (base at rest)
    hinge_axis: np.ndarray           # unit, world
    base_mass_kg: float = 2.5
    friction_mu: float = 0.3
    grasp_stiffness_n_m: float = 3000.0
    table_normal: np.ndarray = None  # unit, world (default +z)
    breakaway_m_s2: float = 2.0      # fingertip ring when the handle breaks away from rest

    @classmethod
    def from_config(cls, section) -> "HingeParams":
        return cls(
            hinge_point=np.array(section.getvec3("point")),
            hinge_axis=np.array(section.getvec3("axis", unit=True)),
            base_mass_kg=section.getfloat("base_mass_kg", 2.5, above=0.0),
            friction_mu=section.getfloat("friction_mu", 0.3, above=0.0),
            grasp_stiffness_n_m=section.getfloat("grasp_stiffness_n_m", 3000.0, above=0.0),
            table_normal=np.array(section.getvec3("table_normal", [0.0, 0.0, 1.0], unit=True)),
            breakaway_m_s2=section.getfloat("breakaway_m_s2", 2.0, minval=0.0),
        )


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
    """

    def __init__(self, params: HingeParams, p_tcp0: np.ndarray):
        self.p = params
        self.axis = unit(params.hinge_axis, "hinge.axis")
        self.n_table = unit(params.table_normal if params.table_normal is not None else np.array([0, 0, 1.0]),
                            "hinge.table_normal")
        self.base_offset = np.zeros(3)
        r = np.asarray(p_tcp0, dtype=float) - params.hinge_point
        r_perp = r - np.dot(r, self.axis) * self.axis
        self.radius = float(np.linalg.norm(r_perp))
        if self.radius < 0.02:
            raise ValueError("hinge.point: the TCP must be at least 2 cm from the hinge axis")
        self.along = float(np.dot(r, self.axis))   # grasp position along the axis, m
        self.e0 = r_perp / self.radius
        self.angle = 0.0
        self.rate = 0.0
        self.force = np.zeros(3)
        self._rest_s = REST_BEFORE_START_S
        self._moving = False

    @property
    def hinge_now(self) -> np.ndarray:
        return self.p.hinge_point + self.base_offset

    def base_displacement(self) -> float:
        return float(np.linalg.norm(self.base_offset))

    def _grasp_deviation(self, p_tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h = self.hinge_now
        r = p_tcp - h
        r_perp = r - np.dot(r, self.axis) * self.axis
        u = r_perp / max(np.linalg.norm(r_perp), 1e-9)
        g = h + self.along * self.axis + self.radius * u
        return p_tcp - g, u

    def step(self, p_tcp: np.ndarray, dt: float) -> bool:
        """Advance by dt with the TCP at p_tcp; returns True when the handle starts to move."""
        k = self.p.grasp_stiffness_n_m
        f_static = self.p.friction_mu * self.p.base_mass_kg * GRAVITY_M_S2
        for _ in range(BASE_SLIDE_ITERATIONS):
            d, u = self._grasp_deviation(p_tcp)
            F = k * d
            F_h = F - np.dot(F, self.n_table) * self.n_table
            f_h = float(np.linalg.norm(F_h))
            if f_h <= f_static:
                break
            # Slide just far enough that the horizontal pull equals kinetic friction.
            self.base_offset += (f_h - f_static) / k * (F_h / f_h)
        d, u = self._grasp_deviation(p_tcp)
        self.force = k * d
        angle = signed_angle(self.e0, u, self.axis)
        self.rate = (angle - self.angle) / dt
        self.angle = angle
        started = False
        if abs(self.rate) > MOTION_START_RATE_RAD_S:
            if not self._moving and self._rest_s >= REST_BEFORE_START_S:
                started = True
            self._moving = True
            self._rest_s = 0.0
        else:
            self._moving = False
            self._rest_s += dt
        return started

    def object_rate_world(self) -> np.ndarray:
        """The handle's angular velocity, world, rad/s."""
        return self.rate * self.axis

    def tangent(self, p_tcp: np.ndarray) -> np.ndarray:
        _, u = self._grasp_deviation(p_tcp)
        return np.cross(self.axis, u)
