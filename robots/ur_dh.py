"""UR e-Series arms, which example-robot-data does not ship (it has the CB-series ur3, ur5, ur10).

An e-Series arm is not its CB namesake: a UR5e's shoulder is 162.5 mm high against a UR5's 89.2 mm,
its wrists are longer, and its reach differs by millimetres to centimetres. With CB kinematics on
an e-Series arm, our FK is centimetres off the controller's and every commanded twist is mapped
to joint rates through the wrong Jacobian. So these models are built from UR's published DH
parameters (Universal Robots, "DH parameters for calculations of kinematics and dynamics"),
chained as Pinocchio revolute-z joints, with the same frames as the CB URDFs: `base_link`, `base`
(the controller's base frame, base_link turned half a turn about z) and `tool0`, the flange.
robots.model makes `base` the world of every UR arm. Masses are UR's; inertias are those of point masses, since
the daemon uses these models for kinematics only.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

# name -> (d1, a2, a3, d4, d5, d6) m; alpha = (pi/2, 0, 0, pi/2, -pi/2, 0) for all
UR_E_DH = {
    "ur3e": (0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "ur5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "ur10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "ur16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
}
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
# link masses, kg (UR's dynamics parameters)
UR_E_MASS = {
    "ur3e": (1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
    "ur5e": (3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
    "ur10e": (7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
    "ur16e": (7.369, 10.45, 4.321, 2.18, 2.033, 0.907),
}
# joint speed limits, rad/s (UR's data sheets: 180 deg/s, or 120 deg/s on the big arms' base joints,
# 360 deg/s on the UR3e's wrists)
UR_E_QD_MAX = {
    "ur3e": (math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi),
    "ur5e": (math.pi,) * 6,
    "ur10e": (2 * math.pi / 3, 2 * math.pi / 3, math.pi, math.pi, math.pi, math.pi),
    "ur16e": (2 * math.pi / 3, 2 * math.pi / 3, math.pi, math.pi, math.pi, math.pi),
}
UR_E_EFFORT = {"ur3e": (56, 56, 28, 12, 12, 12), "ur5e": (150, 150, 150, 28, 28, 28),
               "ur10e": (330, 330, 150, 56, 56, 56), "ur16e": (330, 330, 150, 56, 56, 56)}
JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
          "wrist_3_joint")
LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
Q_LIMIT = (2 * math.pi, 2 * math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi)   # +-, rad (elbow: +-pi)
FLANGE = "tool0"
CONTROLLER_BASE = "base"


def _dh_link(d: float, a: float, alpha: float) -> pin.SE3:
    """The fixed part of a standard DH link after its joint's rotation: Tz(d) Tx(a) Rx(alpha)."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    R = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    return pin.SE3(R, np.array([a, 0.0, d]))


def build_model(name: str) -> pin.Model:
    """The Pinocchio model of a UR e-Series arm `name` (a key of UR_E_DH)."""
    d1, a2, a3, d4, d5, d6 = UR_E_DH[name]
    d, a = (d1, 0.0, 0.0, d4, d5, d6), (0.0, a2, a3, 0.0, 0.0, 0.0)
    model = pin.Model()
    model.name = name
    oMbase = pin.SE3(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))
    model.addFrame(pin.Frame(CONTROLLER_BASE, 0, 0, oMbase, pin.FrameType.OP_FRAME))
    parent, placement = 0, oMbase
    for i in range(6):
        lim = Q_LIMIT[i]
        jid = model.addJoint(parent, pin.JointModelRZ(), placement, JOINTS[i], np.array([UR_E_EFFORT[name][i]], float),
                             np.array([UR_E_QD_MAX[name][i]]), np.array([-lim]), np.array([lim]))
        mass = UR_E_MASS[name][i]
        model.appendBodyToJoint(jid, pin.Inertia(mass, np.zeros(3), np.eye(3) * 1e-3 * mass), pin.SE3.Identity())
        model.addFrame(pin.Frame(LINKS[i], jid, 0, pin.SE3.Identity(), pin.FrameType.BODY))
        parent, placement = jid, _dh_link(d[i], a[i], DH_ALPHA[i])
    model.addFrame(pin.Frame(FLANGE, parent, 0, placement, pin.FrameType.OP_FRAME))
    return model
