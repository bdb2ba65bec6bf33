"""The Cartesian servo, pure: the plan and a joint state in, joint velocities out (rad/s)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tecdard.control.geometry import rotvec_to_matrix

SERVO_MAX_AGE_S = 0.1         # the servo compares a measurement with the plan this far back at most


@dataclass(frozen=True)
class PlanSample:
    """Where the plan has the TCP at `t` (world, SI), and what was commanded for the next tick."""
    t: float
    p_plan: np.ndarray         # the plan's position now, m
    v_plan: np.ndarray         # the plan's velocity now, m/s
    p_cmd: np.ndarray          # the plan's position one tick ahead, m
    R_hold: np.ndarray         # the orientation to hold (world <- TCP) now
    w_ff: np.ndarray           # angular velocity feed-forward of the orientation target, world, rad/s


def joint_velocities(model, js, oMtcp, plan: PlanSample, tick_s: float, max_speed_m_s: float,
                     q_rest: np.ndarray) -> np.ndarray:
    """Joint velocities that take the TCP along the plan: the plan's velocity over the next tick as
    feed-forward, plus feedback on the measurement against the plan at the measurement's own time.

    The plan is at `plan.t`, the measurement at `js.t`, a proprioception period or more earlier.
    Against the plan at `plan.t` the feedback would add gain * v * age, which changes with the age
    each tick (a sawtooth of velocity steps that the IMU's trigger can feel). The TCP's speed is
    capped at `max_speed_m_s` whatever the plan says; redundancy goes towards `q_rest`."""
    v_ff = (plan.p_cmd - plan.p_plan) / tick_s
    age = min(max(plan.t - js.t, 0.0), SERVO_MAX_AGE_S)
    p_ref = plan.p_plan - plan.v_plan * age
    R_ref = rotvec_to_matrix(-plan.w_ff * age) @ plan.R_hold
    tw = model.servo_twist(oMtcp, p_ref, v_ff, R_ref, plan.w_ff)
    speed = float(np.linalg.norm(tw[:3]))
    if speed > max_speed_m_s:              # hard TCP speed bound, whatever the planner said
        tw[:3] *= max_speed_m_s / speed
    return model.dls_velocity(js.q, tw, q_rest)
