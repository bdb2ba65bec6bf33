"""Arm models: TCP FK against Pinocchio's own placement, DLS IK convergence and limit handling."""
import numpy as np
import pinocchio as pin
import pytest

from tecdard.robots.model import READY_Q, ArmModel

POS_TOL_M = 1e-4
ROT_TOL_RAD = 1e-3


def test_tcp_is_flange_times_tool_offset():
    arm = ArmModel("panda", tool_offset=[0.0, 0.0, 0.05])
    q = np.array([0.1, -0.5, 0.2, -2.0, 0.1, 1.8, 0.5])
    oMtcp = arm.fk(q)
    flange = arm.model.getFrameId("panda_hand_tcp", pin.FrameType.BODY) \
        if arm.model.existFrame("panda_hand_tcp", pin.FrameType.BODY) else arm.model.getFrameId("panda_hand_tcp")
    oMf = arm.data.oMf[flange]
    assert np.allclose(oMtcp.translation, oMf.translation + oMf.rotation @ [0, 0, 0.05], atol=1e-12)
    assert np.allclose(oMtcp.rotation, oMf.rotation, atol=1e-12)


@pytest.mark.parametrize("name,q0", [
    ("panda", [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]),
    ("ur5", [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]),
])
def test_dls_servo_converges_to_a_pose(name, q0):
    arm = ArmModel(name)
    q = np.array(q0)
    start = arm.fk(q)
    p_des = start.translation + np.array([0.05, -0.04, 0.03])
    R_des = pin.exp3(np.array([0.0, 0.2, 0.1])) @ start.rotation
    dt = 0.01
    for _ in range(600):
        oMtcp = arm.fk(q)
        tw = arm.servo_twist(oMtcp, p_des, np.zeros(3), R_des, np.zeros(3))
        q = q + arm.dls_velocity(q, tw, np.array(q0)) * dt
    final = arm.fk(q)
    assert np.linalg.norm(final.translation - p_des) < POS_TOL_M
    assert np.linalg.norm(pin.log3(R_des @ final.rotation.T)) < ROT_TOL_RAD
    assert np.all(q >= arm.q_min) and np.all(q <= arm.q_max)


def test_joint_limits_and_rates_are_respected():
    arm = ArmModel("panda")
    q = arm.q_max.copy() - 0.01            # every joint at its upper limit
    q[3] = -1.5
    arm.fk(q)
    qd = arm.dls_velocity(q, np.array([2.0, 2.0, 2.0, 3.0, 3.0, 3.0]))
    at_max = q >= arm.q_max - 0.02
    assert np.all(qd[at_max] <= 0.0)
    assert np.all(np.abs(qd) <= arm.qd_max + 1e-12)


def test_unknown_arm_is_a_clear_error():
    with pytest.raises(ValueError, match="robot.model: unknown arm 'robbie'"):
        ArmModel("robbie")


@pytest.mark.parametrize("name", ["panda", "ur3", "ur5", "ur10", "z1", "xarm7"])
def test_every_arm_loads_and_solves_ik(name):
    arm = ArmModel(name, tool_offset=[0.0, 0.0, 0.05])
    q0 = np.array(READY_Q[name])
    start = arm.fk(q0)
    assert np.all(np.isfinite(start.translation))
    target = pin.SE3(start.rotation, start.translation + np.array([0.02, -0.01, 0.015]))
    q, reached, err = arm.solve_ik(target, q0)
    assert reached, f"{name}: {err * 1e3:.2f} mm"
    assert np.all(q >= arm.q_min - 1e-12) and np.all(q <= arm.q_max + 1e-12)


def test_unreachable_target_is_reported_not_diverging():
    arm = ArmModel("panda")
    q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    far = pin.SE3(np.eye(3), np.array([2.5, 0.0, 0.5]))        # 2.5 m away: out of reach
    q, reached, err = arm.solve_ik(far, q0)
    assert not reached
    assert np.all(np.isfinite(q)) and err > 1.0
    assert np.all(q >= arm.q_min) and np.all(q <= arm.q_max)


@pytest.mark.parametrize("name,dh_name", [("ur3", "UR3"), ("ur5", "UR5"), ("ur10", "UR10"), ("ur3e", "UR3e"),
                                          ("ur5e", "UR5e"), ("ur10e", "UR10e"), ("ur16e", "UR16e")])
def test_ur_models_are_the_controllers_kinematics_in_its_base_frame(name, dh_name):
    """Our UR models (CB URDFs, e-Series from robots/ur_dh.py) against UR's DH parameters, computed
    independently (the fake controller's): a UR arm's world is its controller's base frame, so the
    TCP is the one the controller reports."""
    from tests.fakes.fake_ur import UrKinematics
    arm = ArmModel(name)
    pin.framesForwardKinematics(arm.model, arm.data, pin.neutral(arm.model))
    np.testing.assert_allclose(arm.data.oMf[arm.model.getFrameId("base")].homogeneous, np.eye(4), atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.uniform(-3.0, 3.0, 6)
        T = UrKinematics(dh_name).matrix(q)
        oMtcp = arm.fk(q)
        np.testing.assert_allclose(T[:3, 3], oMtcp.translation, atol=1e-9)
        np.testing.assert_allclose(T[:3, :3], oMtcp.rotation, atol=1e-9)


def test_an_e_series_arm_is_not_its_cb_namesake():
    q = np.array(READY_Q["ur5"])
    assert np.linalg.norm(ArmModel("ur5e").fk(q).translation - ArmModel("ur5").fk(q).translation) > 0.05


def test_arrays_from_a_links_pipe_cross_into_pinocchio_without_a_leak():
    """Issue 37: an array unpickled from a link's pipe (the simulator's and a Franka's states) has a
    dtype object of its own, and eigenpy kept a reference to it on every call: about 130 bytes per
    state, the simulator path's 4.4 MB in 10 minutes at rest. The model hands Pinocchio numpy's own
    float64 dtype (a view, no copy)."""
    import pickle
    import sys
    from multiprocessing.reduction import ForkingPickler
    from tecdard.robots.backend import JointState
    m = ArmModel("panda")
    pose = np.eye(4)
    pose[:3, 3] = [0.4, 0.0, 0.3]
    _, js, _ = pickle.loads(ForkingPickler.dumps(("state", JointState(t=1.0, q=np.zeros(7), qd=np.zeros(7), seq=1,
                                                                      tcp_pose=pose), None)))
    assert js.q.dtype is not np.dtype(np.float64)             # what the pipe gives: its own dtype object
    held = [sys.getrefcount(a.dtype) for a in (js.q, js.qd, js.tcp_pose)]
    for _ in range(100):
        m.measured(js)
        m.dls_velocity(js.q, np.zeros(6))
    assert [sys.getrefcount(a.dtype) for a in (js.q, js.qd, js.tcp_pose)] == held
