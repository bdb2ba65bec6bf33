"""Arm kinematics from example-robot-data URDFs with Pinocchio: TCP forward kinematics and DLS IK."""
from __future__ import annotations

import pathlib
import site
import sys

import numpy as np
import pinocchio as pin

from tecdard.robots import ur_dh

# Damped least-squares IK constants.
DLS_DAMPING = 1e-2          # lambda, m (or rad) equivalent
IK_POS_GAIN_PER_S = 5.0     # feedback on Cartesian position error, 1/s
IK_ROT_GAIN_PER_S = 5.0     # feedback on orientation error, 1/s
IK_POSTURE_GAIN_PER_S = 0.5 # null-space pull towards the home posture, 1/s
JOINT_LIMIT_MARGIN_RAD = 0.02
IK_MAX_ITERATIONS = 300
IK_STALL_ITERATIONS = 25    # no progress for this many iterations: unreachable
IK_MAX_STEP_RAD = 0.2

# Arms by name: URDF path under example-robot-data's robots/ and the flange frame; or None for the
# UR e-Series arms, built from UR's DH parameters (robots/ur_dh.py: example-robot-data has none).
ARMS = {
    "panda": ("panda_description/urdf/panda.urdf", "panda_hand_tcp"),
    # FR3: Franka's DH parameters and hand are the Panda's; its joint ranges are its own (FR3_LIMITS)
    "fr3": ("panda_description/urdf/panda.urdf", "panda_hand_tcp"),
    "ur3": ("ur_description/urdf/ur3_robot.urdf", "tool0"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0"),
    "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
    "z1": ("z1_description/urdf/z1.urdf", "gripperStator"),
    "xarm7": ("xarm_description/urdf/xarm7.urdf", "link7"),
    **{name: (None, ur_dh.FLANGE) for name in ur_dh.UR_E_DH},
}
# A well-conditioned "ready" posture per arm (rad): smallest Jacobian singular value >= 0.1.
READY_Q = {
    "panda": (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785),
    "fr3": (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785),
    "ur3": (0.0, -1.2, 1.5, -1.9, -1.57, 0.0),
    "ur5": (0.0, -1.2, 1.5, -1.9, -1.57, 0.0),
    "ur10": (0.0, -1.2, 1.5, -1.9, -1.57, 0.0),
    "z1": (0.0, 1.2, -1.0, -0.3, 0.0, 0.0),
    "xarm7": (0.0, -0.4, 0.0, 0.6, 0.0, 1.0, 0.0),
    **{name: (0.0, -1.2, 1.5, -1.9, -1.57, 0.0) for name in ur_dh.UR_E_DH},
}


# FR3's joint position limits (rad), from Franka's FR3 datasheet: narrower than the Panda's in
# places (joint 6 starts at 0.5445 rad), and the arm refuses motion outside them. Joint velocity
# limits stay the Panda's, which franky itself enforces on every motion (2.175 / 2.61 rad/s).
FR3_LIMITS = {
    "q_min": (-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159),
    "q_max": (2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159),
}


# A UR arm's world is its controller's base frame (UR's DH base; ur_description's `base`, which is
# `base_link` turned half a turn about z): the frame of the pendant's TCP pose and of ur-rtde's
# getActualTCPPose, so positions the daemon takes and reports read as a UR user reads them.
UR_ARMS = ("ur3", "ur5", "ur10", *ur_dh.UR_E_DH)


def reroot(model: pin.Model, frame: str) -> None:
    """Make the fixed frame `frame` the model's world: everything attached to the universe is
    placed relative to it instead (the joints' motion is unchanged)."""
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    fMo = data.oMf[model.getFrameId(frame)].inverse()
    for j in range(1, model.njoints):
        if model.parents[j] == 0:
            model.jointPlacements[j] = fMo * model.jointPlacements[j]
    for f in model.frames:
        if f.parentJoint == 0:
            f.placement = fMo * f.placement


class UnknownRobotError(ValueError):
    pass


def robots_dir() -> pathlib.Path:
    """example-robot-data's robots/ folder inside the installed cmeel prefix."""
    candidates = [pathlib.Path(p) for p in site.getsitepackages()] + [pathlib.Path(p) for p in sys.path if p]
    for base in candidates:
        path = base / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if path.is_dir():
            return path
    raise FileNotFoundError("example-robot-data: robots/ not found under any site-packages cmeel.prefix")


def user_urdf(path: str, tcp_link: str | None) -> tuple[pin.Model, str, str]:
    """A user's URDF (robot.urdf) as a Pinocchio model, its flange link and its name for messages;
    UnknownRobotError in one line for a file that cannot be the arm: unreadable, not URDF, no
    `tcp_link`, no joint, or a joint the daemon cannot servo (continuous, floating, planar)."""
    if not tcp_link:
        raise UnknownRobotError("robot.tcp_link: required with robot.urdf (the link the TCP is offset from)")
    file = pathlib.Path(path)
    if not file.is_file():
        raise UnknownRobotError(f"robot.urdf: {path}: no such file")
    try:
        model = pin.buildModelFromUrdf(str(file))
    except Exception as exc:          # pinocchio's parser: a ValueError or RuntimeError with a long message
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise UnknownRobotError(f"robot.urdf: {file.name} does not parse as URDF ({first})") from None
    if model.njoints < 2:
        raise UnknownRobotError(f"robot.urdf: {file.name} has no moving joint")
    for j in range(1, model.njoints):
        if model.joints[j].nq != 1 or model.joints[j].nv != 1:
            raise UnknownRobotError(f"robot.urdf: {file.name}: joint {model.names[j]!r} is not revolute or "
                                    f"prismatic with limits ({model.joints[j].shortname()})")
    no_limit = [model.names[j] for j in range(1, model.njoints)
                if not model.velocityLimit[model.joints[j].idx_v] > 0.0
                or not model.upperPositionLimit[model.joints[j].idx_q] > model.lowerPositionLimit[model.joints[j].idx_q]]
    if no_limit:
        raise UnknownRobotError(f"robot.urdf: {file.name}: joint {no_limit[0]!r} has no position range or velocity "
                                "limit (<limit lower upper velocity>): a joint state's jump cannot be judged")
    if not model.existFrame(tcp_link):
        links = sorted({f.name for f in model.frames if f.type == pin.FrameType.BODY})
        raise UnknownRobotError(f"robot.tcp_link: {tcp_link!r} is no link of {file.name} (links: "
                                f"{', '.join(links)[:300]})")
    return model, tcp_link, file.name


def f64(a) -> np.ndarray:
    """`a` as float64 with numpy's own float64 dtype object (a view, no copy). An array unpickled
    from a link's pipe (the simulator's, a Franka's states) carries a dtype object of its own, and
    every such array that crosses into Pinocchio (eigenpy 3.13) leaked about 130 bytes: the
    simulator path's RSS grew 4.4 MB in 10 minutes at rest (issue 37)."""
    return np.asarray(a, dtype=np.float64)


class ArmModel:
    """A fixed-base arm: Pinocchio model (gripper fingers locked), TCP frame = flange * tool offset.

    Load once; each thread that calls FK/IK makes its own `ArmModel.clone()` so
    that every `pin.Data` has a single owner.
    """

    def __init__(self, name: str, tool_offset: np.ndarray | None = None, tool_quat=None, urdf: str | None = None,
                 tcp_link: str | None = None):
        """An arm of ARMS by `name`, or a user's URDF (`urdf`, its flange the link `tcp_link`; `name`
        only labels it)."""
        if urdf is not None:
            full, flange, source = user_urdf(urdf, tcp_link)
        elif name not in ARMS:
            raise UnknownRobotError(f"robot.model: unknown arm {name!r}; known: {', '.join(sorted(ARMS))}")
        else:
            rel, flange = ARMS[name]
            source = f"{name} (UR's DH parameters)" if rel is None else (robots_dir() / rel).name
            full = ur_dh.build_model(name) if rel is None else pin.buildModelFromUrdf(str(robots_dir() / rel))
        # Lock everything that is not a revolute arm joint (gripper fingers).
        lock = [j for j in range(1, full.njoints) if "finger" in full.names[j] or "gripper" in full.names[j].lower()]
        if lock:
            model = pin.buildReducedModel(full, lock, pin.neutral(full))
        else:
            model = full
        if name in UR_ARMS and urdf is None:
            reroot(model, ur_dh.CONTROLLER_BASE)
        self.name = name
        self.joint_names = [str(n) for n in model.names[1:]]       # in q's order
        self.tool_offset = [0.0, 0.0, 0.0] if tool_offset is None else [float(x) for x in tool_offset]   # flange -> TCP, m
        self.tool_quat = [0.0, 0.0, 0.0, 1.0] if tool_quat is None else [float(x) for x in tool_quat]   # (x, y, z, w)
        self.model = model
        self.nq = model.nq
        if model.existFrame(flange, pin.FrameType.BODY):
            flange_id = model.getFrameId(flange, pin.FrameType.BODY)
        elif model.existFrame(flange):
            flange_id = model.getFrameId(flange)
        else:
            raise UnknownRobotError(f"robot.model: frame {flange!r} not in {source}")
        offset = pin.SE3.Identity()
        if tool_offset is not None:
            offset.translation = np.asarray(tool_offset, dtype=float)
        if tool_quat is not None:
            offset.rotation = pin.Quaternion(np.asarray(tool_quat, dtype=float)).toRotationMatrix()
        parent = model.frames[flange_id]
        tcp = pin.Frame("tecdar_tcp", parent.parentJoint, flange_id, parent.placement * offset,
                        pin.FrameType.OP_FRAME)
        self.tcp_id = model.addFrame(tcp)
        if name == "fr3":
            model.lowerPositionLimit[:] = FR3_LIMITS["q_min"]
            model.upperPositionLimit[:] = FR3_LIMITS["q_max"]
        self.q_min = model.lowerPositionLimit.copy()
        self.q_max = model.upperPositionLimit.copy()
        self.qd_max = model.velocityLimit.copy()
        self.qd_min = -self.qd_max
        self.data = model.createData()

    def clone(self) -> "ArmModel":
        other = object.__new__(ArmModel)
        other.__dict__.update(self.__dict__)
        other.data = self.model.createData()
        return other

    def fk(self, q: np.ndarray) -> pin.SE3:
        """oMtcp: TCP placement in the world (base) frame."""
        pin.framesForwardKinematics(self.model, self.data, f64(q))
        return self.data.oMf[self.tcp_id].copy()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """6 x nq TCP Jacobian, rows [v; w] in LOCAL_WORLD_ALIGNED (call after fk at the same q)."""
        return pin.computeFrameJacobian(self.model, self.data, f64(q), self.tcp_id, pin.LOCAL_WORLD_ALIGNED)

    def fk_twist(self, q: np.ndarray, qd: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        """oMtcp and the TCP twist [v; w] (world-aligned, m/s and rad/s)."""
        oMtcp = self.fk(q)
        return oMtcp, self.jacobian(q) @ qd

    def measured(self, js) -> tuple[pin.SE3, np.ndarray]:
        """oMtcp and the TCP twist [v; w] of a JointState (robots.backend): the pose and the twist
        the robot reports when it reports them (a UR controller's carry the arm's own kinematic
        calibration, which generic URDF kinematics miss by millimetres), else from the joints."""
        oMtcp, twist = self.fk_twist(js.q, js.qd)
        if js.tcp_pose is not None:
            oMtcp = pin.SE3(f64(js.tcp_pose))
        return oMtcp, (twist if js.tcp_twist is None else js.tcp_twist)

    def dls_velocity(self, q: np.ndarray, twist: np.ndarray, q_home: np.ndarray | None = None) -> np.ndarray:
        """Joint velocity for a desired TCP twist [v; w] (world-aligned) by damped least squares.

        Respects joint velocity limits by uniform scaling and stops joints moving
        further into a position limit.
        """
        J = self.jacobian(q)
        JJt = J @ J.T + (DLS_DAMPING**2) * np.eye(6)
        qd = J.T @ np.linalg.solve(JJt, twist)
        if q_home is not None:
            N = np.eye(self.nq) - J.T @ np.linalg.solve(JJt, J)
            qd += N @ (IK_POSTURE_GAIN_PER_S * (q_home - q))
        at_min = (q <= self.q_min + JOINT_LIMIT_MARGIN_RAD) & (qd < 0)
        at_max = (q >= self.q_max - JOINT_LIMIT_MARGIN_RAD) & (qd > 0)
        qd[at_min | at_max] = 0.0
        scale = np.max(np.abs(qd) / self.qd_max)
        if scale > 1.0:
            qd /= scale
        return qd

    def solve_ik(self, oMdes: pin.SE3, q0: np.ndarray, tol_m: float = 1e-5, tol_rad: float = 1e-4,
                 max_iter: int = IK_MAX_ITERATIONS) -> tuple[np.ndarray, bool, float]:
        """Joint positions reaching oMdes from q0 by damped least squares, within joint limits.

        Returns (q, reached, position error m). An unreachable target (out of reach, against a
        joint limit) ends with reached=False and the closest configuration found, never NaN.
        """
        q = np.clip(np.asarray(q0, dtype=float).copy(), self.q_min, self.q_max)
        best_q, best_err = q.copy(), np.inf
        stall = 0
        for _ in range(max_iter):
            oM = self.fk(q)
            err_p = oMdes.translation - oM.translation
            err_r = pin.log3(oMdes.rotation @ oM.rotation.T)
            e_p, e_r = float(np.linalg.norm(err_p)), float(np.linalg.norm(err_r))
            if e_p < tol_m and e_r < tol_rad:
                return q, True, e_p
            score = e_p + 0.1 * e_r
            if score < best_err - 1e-9:
                best_q, best_err, stall = q.copy(), score, 0
            else:
                stall += 1
                if stall > IK_STALL_ITERATIONS:
                    break
            J = self.jacobian(q)
            e = np.concatenate([err_p, err_r])
            dq = J.T @ np.linalg.solve(J @ J.T + (DLS_DAMPING ** 2) * np.eye(6), e)
            # joints pinned at a limit and pushed further: take them out and solve with the rest
            pinned = ((q <= self.q_min + 1e-9) & (dq < 0)) | ((q >= self.q_max - 1e-9) & (dq > 0))
            if pinned.any():
                Jf = J.copy()
                Jf[:, pinned] = 0.0
                dq = Jf.T @ np.linalg.solve(Jf @ Jf.T + (DLS_DAMPING ** 2) * np.eye(6), e)
            step = np.max(np.abs(dq))
            if step > IK_MAX_STEP_RAD:
                dq *= IK_MAX_STEP_RAD / step
            q = np.clip(q + dq, self.q_min, self.q_max)
        oM = self.fk(best_q)
        return best_q, False, float(np.linalg.norm(oMdes.translation - oM.translation))

    def servo_twist(self, oMtcp: pin.SE3, p_des: np.ndarray, v_des: np.ndarray, R_des: np.ndarray,
                    w_des: np.ndarray) -> np.ndarray:
        """Feed-forward twist plus proportional correction towards (p_des, R_des)."""
        v = v_des + IK_POS_GAIN_PER_S * (p_des - oMtcp.translation)
        w = w_des + IK_ROT_GAIN_PER_S * pin.log3(R_des @ oMtcp.rotation.T)
        return np.concatenate([v, w])
