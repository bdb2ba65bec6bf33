"""The simulated robot: proprioception rate and noise, latency and lag, reported twist, determinism."""
import numpy as np
import pytest

from tecdard.sim.imu import SimImu, SimImuParams
from tecdard.robots.model import ArmModel
from tecdard.sim.robot import SimRobot, SimRobotParams
from tecdard.sim.world import HingeParams, HingeWorld

Q_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


class ManualClock:
    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t


def run(seed, seconds=2.0, with_world=True):
    clock = ManualClock()
    arm = ArmModel("panda")
    imu = SimImu(SimImuParams(), seed=seed)
    world = (lambda p, R: HingeWorld(HingeParams(np.array([0.157, 0.0, 0.487]), np.array([0.0, 1.0, 0.0])), p)) \
        if with_world else None
    robot = SimRobot(arm, SimRobotParams(q_home=Q_HOME.copy()), world, imu, seed=seed, clock=clock)
    states, chunks = [], []
    for k in range(int(seconds / 0.02)):
        js = robot.read_state()
        oM = arm.fk(js.q)
        twist = np.concatenate([[0.0, 0.0, 0.02], np.zeros(3)]) if k < 60 else np.zeros(6)
        tw = arm.servo_twist(oM, oM.translation, twist[:3], oM.rotation, np.zeros(3))
        robot.command_joint_velocity(arm.dls_velocity(js.q, tw, Q_HOME))
        clock.t += 0.02
        robot.advance_to(clock.t)
        states.append(robot.read_state())
        while (c := imu.read(0.0)) is not None:
            chunks.append(c)
    return robot, states, chunks


@pytest.mark.slow
def test_as_fast_as_possible_is_deterministic():
    a_robot, a_states, a_chunks = run(seed=5)
    b_robot, b_states, b_chunks = run(seed=5)
    assert np.array_equal(a_states[-1].q, b_states[-1].q)
    assert np.array_equal(np.vstack([c[1] for c in a_chunks]), np.vstack([c[1] for c in b_chunks]))
    assert a_robot.truth().handle_angle_rad == b_robot.truth().handle_angle_rad
    c_robot, c_states, _ = run(seed=6)
    assert not np.array_equal(a_states[-1].q, c_states[-1].q)      # the seed matters (encoder noise)


def test_proprioception_rate_noise_and_reported_twist():
    robot, states, chunks = run(seed=1, seconds=2.0)
    first, last = states[5], states[-1]
    rate = (last.seq - first.seq) / (last.t - first.t)      # seq counts every proprioception sample
    assert rate == pytest.approx(65.0, rel=0.05)
    arm = ArmModel("panda")
    s = states[30]                                          # moving at 20 mm/s up
    arm.fk(s.q)
    J = arm.jacobian(s.q)
    assert np.linalg.norm(s.tcp_twist[:3] - (J @ s.qd)[:3]) < 2e-3
    assert s.tcp_twist[2] == pytest.approx(0.02, abs=3e-3)
    n = sum(len(c[0]) for c in chunks)
    assert n == pytest.approx(6667 * 2.0, rel=0.02)         # IMU at its ODR


def test_commands_take_effect_after_latency_through_the_lag():
    clock = ManualClock()
    arm = ArmModel("panda")
    p = SimRobotParams(q_home=Q_HOME.copy(), command_latency_s=0.01, tracking_tau_s=0.02, encoder_noise_rad=0.0,
                       proprio_rate_hz=1000.0)
    robot = SimRobot(arm, p, clock=clock)
    qd = np.zeros(7)
    qd[0] = 0.1
    robot.command_joint_velocity(qd)
    clock.t += 0.009
    robot.advance_to(clock.t)
    assert abs(robot.read_state().qd[0]) < 1e-12            # not yet: latency
    clock.t += 0.021                                        # 20 ms after it took effect: one time constant
    robot.advance_to(clock.t)
    assert robot.read_state().qd[0] == pytest.approx(0.1 * (1 - np.exp(-1)), rel=0.1)


def test_the_arm_stops_by_itself_when_commands_cease():
    """A stalled controller must not leave the arm moving: like a real velocity interface, the
    simulated arm zeroes its command after command_timeout_s without a new one."""
    clock = ManualClock()
    arm = ArmModel("panda")
    robot = SimRobot(arm, SimRobotParams(q_home=Q_HOME.copy(), encoder_noise_rad=0.0), clock=clock)
    qd = np.zeros(7)
    qd[0] = 0.2
    for _ in range(10):                       # commanded every 20 ms: it keeps turning
        robot.command_joint_velocity(qd)
        clock.t += 0.02
        robot.advance_to(clock.t)
    assert robot.read_state().qd[0] == pytest.approx(0.2, rel=1e-3) and robot.watchdog_stops == 0
    q_quiet = robot.read_state().q[0]
    clock.t += 1.0                            # then the controller goes quiet for a second
    robot.advance_to(clock.t)
    js = robot.read_state()
    assert robot.watchdog_stops == 1
    assert abs(js.qd[0]) < 1e-6
    # it coasted for about the timeout (0.1 s) and the tracking lag, not the whole second
    assert 0.2 * 0.1 < js.q[0] - q_quiet < 0.2 * 0.15
