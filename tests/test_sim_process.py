"""The simulation in its own process: state, commands, IMU chunks and truth cross the pipes; it stops cleanly."""
import time

import numpy as np
import pytest

from tecdard.sim.imu import SimImuParams
from tecdard.sim.robot import SimRobotParams
from tecdard.sim.process import SimProcess, SimProcessError, SimSpec
from tecdard.sim.world import HingeParams

Q_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


@pytest.mark.slow
def test_the_child_streams_state_and_imu_follows_commands_and_stops():
    spec = SimSpec(arm="panda", tool_offset=[0.0, 0.0, 0.0], tool_quat=[0.0, 0.0, 0.0, 1.0],
                   robot=SimRobotParams(q_home=Q_HOME.copy()), imu=SimImuParams(),
                   hinge=HingeParams(np.array([0.157, 0.0, 0.487]), np.array([0.0, 1.0, 0.0])))
    sim = SimProcess(spec, nq=7)
    sim.start()
    try:
        js0 = sim.read_state()
        assert js0.q.shape == (7,) and sim.truth() is not None
        samples, t_end, stamps = 0, time.monotonic() + 0.5, []
        while time.monotonic() < t_end:
            sim.command_joint_velocity(np.r_[0.2, np.zeros(6)])     # the base joint turns
            chunk = sim.imu.read(0.05)
            if chunk is not None:
                t, gyro, accel = chunk
                assert gyro.shape == accel.shape == (len(t), 3)
                samples += len(t)
                stamps.append(t)
        # the forwarder joins the physics slices into fewer messages: none lost, none repeated
        dt = np.diff(np.concatenate(stamps))
        assert np.all(dt > 0) and np.all(dt < 2.0 / spec.imu.odr_hz), (dt.min(), dt.max())
        js1 = sim.read_state()
        assert js1.seq > js0.seq and abs(js1.t - time.monotonic()) < 0.1     # the shared monotonic clock
        assert js1.q[0] - js0.q[0] > 0.05                                    # 0.2 rad/s for about 0.5 s
        assert samples > 0.3 * 6667
        # wait_state hands over each new state as it comes (the estimator's proprioception thread)
        seqs, t_end = [js1.seq], time.monotonic() + 0.3
        while time.monotonic() < t_end:
            seqs.append(sim.wait_state(seqs[-1], 0.2).seq)
        assert np.all(np.diff(seqs) > 0)
        assert len(seqs) - 1 >= 0.7 * 0.3 * spec.robot.proprio_rate_hz
    finally:
        sim.stop()
    assert sim.exited.wait(2.0)
    with pytest.raises(SimProcessError):
        sim.wait_state(seqs[-1], 0.2)


def test_one_read_of_the_imu_pipe_takes_every_chunk_waiting():
    """Issue 37: the acquisition thread naps up to 20 ms at rest while the child sends a chunk per
    10 ms slice; a read that took one chunk fell behind until the child dropped half the samples."""
    import multiprocessing
    import types
    from tecdard.sim.process import PipeImuSource
    rx, tx = multiprocessing.Pipe(duplex=False)
    link = types.SimpleNamespace(imu_rx=rx, exited=types.SimpleNamespace(is_set=lambda: False))
    source = PipeImuSource(link)
    t = np.arange(201) * 1.5e-4
    for part in np.array_split(np.arange(len(t)), 3):          # three slices' chunks wait in the pipe
        tx.send((t[part], np.ones((len(part), 3)), np.zeros((len(part), 3))))
    got_t, gyro, accel = source.read(0.1)
    np.testing.assert_array_equal(got_t, t)
    assert gyro.shape == accel.shape == (len(t), 3)
    assert source.read(0.01) is None
    rx.close()
    tx.close()


def test_the_childs_wakes_sit_half_a_step_off_the_physics_grid_so_every_slice_is_ten_steps():
    """The child integrates whole 1 ms steps up to each wake. Woken half a step after the grid
    (on_grid), sleep's lateness of up to 0.45 ms leaves every 10 ms slice at 10 steps; woken on a
    step's edge (the phase a start once set by chance) the same lateness made 9- and 11-step
    slices, 60- and 73-sample IMU chunks, which the estimator took two at a time."""
    from tecdard.sim.process import on_grid
    from tecdard.sim.robot import PHYSICS_RATE_HZ, PHYSICS_WAKE_S
    dt = 1.0 / PHYSICS_RATE_HZ
    rng = np.random.default_rng(5)
    lateness = rng.uniform(0.0, 0.45 * dt, 2000)

    def steps(first_wake: float) -> set[int]:
        t_physics, counts = 1000.0, set()
        for k, late in enumerate(lateness):
            now = first_wake + (k + 1) * PHYSICS_WAKE_S + late
            n = int((now - t_physics) / dt)
            t_physics += n * dt
            counts.add(n)
        return counts

    assert on_grid(1000.0) == 1000.0 + 0.5 * dt
    assert steps(on_grid(1000.0)) == {10}
    assert steps(1000.0 + 0.999 * dt) > {10}           # on a step's edge: 9 and 11 as well
