"""The control thread, ticked directly: its estimator checks (divergence, contact jumps), faults, and the servo."""

import numpy as np
import pytest

from tecdard.control.pipeline import ContactEstimate
from tecdard.control.tasks import ApproachTask
from tecdard.robots.backend import JointState, RobotBackend
from tecdard.sim.world import SimTruth
from tecdard.robots.model import READY_Q, ArmModel
from tecdard.control.modes import Mode
from tecdard.runtime.control_thread import ControlParams, ControlThread
from tecdard.runtime.messages import LatestValue, Outbox, StartTask

AXIS = np.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def model():
    return ArmModel("panda")


def control_thread(model, ring=None, **params):
    return ControlThread(ControlParams(**params), model, robot=RobotBackend(), ring=ring, contact=LatestValue(),
                         directive=LatestValue(), outbox=Outbox(4096), q_home=READY_Q["panda"], robot_name="sim")


def control(model, **params):
    """A control thread with an approach running (its task set directly, no tick yet)."""
    ct = control_thread(model, **params)
    ct.runner.task = ApproachTask("approach-1", np.array([0.0, 0.0, -1.0]), 0.02, 0.05, 0.1)
    ct.runner.mode = Mode.BUSY
    ct.runner.task_t0 = 0.0
    return ct


def estimate(p, converged=True, nis_ratio=0.5):
    p = np.asarray(p, float)
    return ContactEstimate(t=1.0, onset_t=0.5, p=p, std=np.full(3, 1e-3), cov=np.eye(3) * 1e-6, axis=AXIS,
                           converged=converged, nis=1.0, steps=1000, nis_ratio=nis_ratio)


def drained_events(ct, *kinds):
    out = []
    while not ct.outbox.empty():
        kind, *rest = ct.outbox.get_nowait()
        if kind == "event" and rest[0]["kind"] in kinds:
            out.append(rest[0])
    return out


def stops(ct):
    return drained_events(ct, "protective_stop")


JS = JointState(t=0.0, q=READY_Q["panda"], qd=np.zeros(7), seq=0)


def test_a_converged_estimate_that_jumps_is_a_protective_stop(model):
    ct = control(model, max_contact_jump_m=0.02)
    ct.runner.check(JS.tcp_force, estimate([0.50, 0.0, 0.20]))
    ct.runner.check(JS.tcp_force, estimate([0.51, 0.0, 0.20]))        # 10 mm: within the limit
    assert stops(ct) == []
    ct.runner.check(JS.tcp_force, estimate([0.51, 0.0, 0.235]))       # 35 mm in one tick
    (stop,) = stops(ct)
    assert stop["cause"] == "contact_jump" and stop["jump_m"] == pytest.approx(0.035)
    assert ct.runner.task is None and ct.runner.mode is Mode.STOPPING


def test_jumps_before_convergence_or_along_the_edge_are_no_stop(model):
    ct = control(model, max_contact_jump_m=0.02)
    ct.runner.check(JS.tcp_force, estimate([0.50, 0.0, 0.20], converged=False))
    ct.runner.check(JS.tcp_force, estimate([0.60, 0.0, 0.20]))        # the estimate was still converging
    ct.runner.check(JS.tcp_force, estimate([0.60, 0.3, 0.20]))        # along the edge: unobservable, no evidence
    assert stops(ct) == [] and ct.runner.task is not None


def test_innovations_far_beyond_their_expected_size_are_a_protective_stop(model):
    ct = control(model, max_nis_ratio=10.0)
    ct.runner.check(JS.tcp_force, estimate([0.5, 0.0, 0.2], nis_ratio=9.0))
    assert stops(ct) == []
    ct.runner.check(JS.tcp_force, estimate([0.5, 0.0, 0.2], nis_ratio=40.0))
    (stop,) = stops(ct)
    assert stop["cause"] == "divergence" and stop["nis_ratio"] == 40.0


class HoldingRobot:
    def __init__(self):
        self.holds = 0

    def hold(self):
        self.holds += 1


def test_a_failing_tick_holds_the_arm_and_ends_the_task(model):
    """A bug in a tick must neither leave the arm moving nor kill the control thread."""
    ct = control(model)
    ct.robot = HoldingRobot()
    ct._internal_fault(KeyError("direction"))
    (stop,) = stops(ct)
    assert stop["cause"] == "internal" and "KeyError" in stop["message"]
    assert ct.robot.holds == 1 and ct.runner.task is None and ct.runner.mode is Mode.IDLE


def test_a_point_contact_result_ends_the_task_with_the_sim_truth():
    """An approach that ends on a point contact reports no axis; its end event still carries the truth.
    (It once raised in the truth and the task vanished without an end event.)"""
    from tecdard.sim.backend import with_truth
    truth = SimTruth(np.array([0.3, 0.0, 0.3]), np.array([0.0, 1.0, 0.0]), 0.1, 0.0, {"contacts": 1})
    ev = with_truth({"kind": "task_done", "task": "approach-1", "result": {"p": [0.3, 0.0, 0.3], "axis": None}}, truth)
    assert ev["result"]["sim"]["contacts"] == 1 and ev["result"]["p"] == [0.3, 0.0, 0.3]
    failed = with_truth({"kind": "task_failed", "task": "rotate-1", "error": "x"}, truth)
    assert failed["sim"]["hinge_axis"] == [0.0, 1.0, 0.0] and "result" not in failed
    assert with_truth({"kind": "contact_onset"}, truth) == {"kind": "contact_onset"}


def test_a_failing_annotation_never_costs_the_task_its_end_event():
    """The simulator's truth is added on the main thread; a failure there publishes the event as it is."""
    from tecdard.runtime.main_loop import MainLoop, ZenohDoor

    class Pub:
        def __init__(self):
            self.texts = []

        def put(self, text):
            self.texts.append(text)

    def broken(event):
        raise RuntimeError("world gone")

    outbox = Outbox(16)
    outbox.put("event", {"t": 1.0, "kind": "task_failed", "task": "approach-1", "error": "no contact"})
    events = Pub()
    main = MainLoop(None, None, outbox, (ZenohDoor(None, Pub(), Pub(), events),), annotate=broken)
    assert main.publish_telemetry(0.0) == 1
    assert '"kind":"task_failed"' in events.texts[0] and '"sim"' not in events.texts[0]


class LaggingArm(RobotBackend):
    """A perfect velocity-controlled arm whose joint state reaches the controller `age` late,
    the age changing from tick to tick as 65 Hz samples met by 50 Hz ticks (and a loaded machine) do."""

    def __init__(self, q0, ages):
        self.q, self.qd, self.t = q0.copy(), np.zeros(len(q0)), 0.0
        self.history = [(0.0, q0.copy(), np.zeros(len(q0)))]
        self.ages = ages
        self.seq = 0

    def advance(self, t):
        self.q = self.q + self.qd * (t - self.t)
        self.t = t
        self.history.append((t, self.q.copy(), self.qd.copy()))

    def read_state(self):
        t_meas = max(self.t - next(self.ages), 0.0)
        t0, q0, qd = next(h for h in reversed(self.history) if h[0] <= t_meas)
        self.seq += 1
        return JointState(t=t_meas, q=q0 + qd * (t_meas - t0), qd=qd, seq=self.seq)

    def command_joint_velocity(self, qd):
        self.qd = np.asarray(qd, float).copy()

    def hold(self):
        self.qd = np.zeros(len(self.q))


class FreshRing:
    total, last_t, overwritten = 1, 0.0, 0


def cruise_tcp_speeds(model, ages):
    """A free approach down at 20 mm/s, ticked exactly every 20 ms; the TCP speeds it commands in cruise."""
    ct = control_thread(model, ring=FreshRing())
    arm = ct.robot = LaggingArm(np.array(READY_Q["panda"], float), ages)
    ct.submit(StartTask(None, "approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.05,
                                           "stop_angle_deg": 10.0}))
    speeds = []
    for k in range(1, 90):
        now = 0.02 * k
        arm.advance(now)
        FreshRing.last_t = now
        ct.tick(now)
        speeds.append(float(-model.fk_twist(arm.q, arm.qd)[1][2]))
    assert ct.runner.task is not None and ct.runner.task.status.phase == "approach"
    return np.array(speeds[40:])


def test_the_servo_compares_a_late_measurement_with_the_plan_at_its_time(model):
    """The plan is at the tick's time, the joint state up to tens of ms older. Compared with the
    plan at `now` the feedback adds gain * v * age, a velocity step each tick the age changes,
    which the IMU's trigger feels as an impact; compared at the measurement's time it adds nothing."""
    rng = np.random.default_rng(1)
    ages = iter(lambda: float(rng.uniform(0.0, 0.035)), None)
    speeds = cruise_tcp_speeds(model, ages)
    assert np.all(np.abs(speeds - 0.02) < 2e-4), (speeds.min(), speeds.max())


def test_the_trigger_arms_only_once_the_plan_has_moved_steadily_for_a_while(model):
    """An approach from rest: the arm follows the plan with a lag, so the trigger arms TRIGGER_SETTLE_S
    after the plan reaches its constant speed, not at once; its start is no impact."""
    from tecdard.control.runner import TRIGGER_SETTLE_S
    ct = control_thread(model, ring=FreshRing())
    arm = ct.robot = LaggingArm(np.array(READY_Q["panda"], float), iter(lambda: 0.0, None))
    ct.submit(StartTask(None, "approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.05,
                                           "stop_angle_deg": 10.0}))
    steady_at = armed_at = None
    for k in range(1, 60):
        now = 0.02 * k
        arm.advance(now)
        FreshRing.last_t = now
        ct.tick(now)
        if steady_at is None and ct.runner.planner.steady(0.02):
            steady_at = now
        if ct.directive.get().armed and armed_at is None:
            armed_at = now
    assert steady_at is not None and armed_at is not None
    assert TRIGGER_SETTLE_S <= armed_at - steady_at <= TRIGGER_SETTLE_S + 0.021


def test_a_late_tick_judges_imu_staleness_on_the_next_tick_once(model):
    """A tick that starts late means the daemon itself stalled, and the IMU's samples may still be
    queued behind it: the stale-IMU stop waits one tick, then stops all the same if they stay away."""
    from tecdard.control.safety import STALE_JUDGE_LATE_S

    class Ring:
        total, last_t, overwritten = 1, 0.0, 0

    ct = control(model, imu_stale_s=0.05, ring=Ring())
    ct._late_s = STALE_JUDGE_LATE_S + 0.05
    ct._check_sensors(0.08, np.zeros(3), 0.08)                       # 80 ms without a sample, but this tick is late
    assert "imu_stale" not in ct.faults and stops(ct) == []
    Ring.last_t = 0.09                           # the samples were only queued: no fault at all
    ct._late_s = 0.0
    ct._check_sensors(0.10, np.zeros(3), 0.10)
    assert "imu_stale" not in ct.faults and stops(ct) == []
    ct._late_s = STALE_JUDGE_LATE_S + 0.05       # late again, and this time the IMU has gone
    ct._check_sensors(0.20, np.zeros(3), 0.20)
    assert "imu_stale" not in ct.faults
    ct._check_sensors(0.22, np.zeros(3), 0.22)                       # a second late tick judges it: a protective stop
    assert "imu_stale" in ct.faults and [s["cause"] for s in stops(ct)] == ["imu_stale"]


def test_a_thread_named_in_the_os_shows_its_name_in_proc():
    """Issue 37: the daemon's threads carry their names into /proc (top -H, ps -L), truncated to 15 characters."""
    import threading
    from tecdard.host import name_os_thread
    seen = {}

    def body():
        seen["ok"] = name_os_thread("imu-acquisition-long-name")
        seen["comm"] = open(f"/proc/self/task/{threading.get_native_id()}/comm").read().strip()
    th = threading.Thread(target=body)
    th.start()
    th.join()
    assert seen == {"ok": True, "comm": "imu-acquisition"}
    assert open(f"/proc/self/task/{threading.get_native_id()}/comm").read().strip() != "imu-acquisition"


def test_a_rotate_that_diverges_says_the_likely_cause_its_direction(model):
    """Issue 50 item 9: a second rotate with the first's direction (the handle has turned since) failed 3 times
    in 3 with "estimator innovations 11x" and nothing more."""
    from tecdard.control.rotate import RotateTask
    ct = control(model, max_nis_ratio=10.0)
    ct.runner.task = RotateTask("rotate-1", 0.5, 0.02, 0.005, np.array([0.0, 0.0, 1.0]), "arc")
    ct.runner.check(JS.tcp_force, estimate([0.5, 0.0, 0.2], nis_ratio=11.0))
    (stop,) = stops(ct)
    assert stop["cause"] == "divergence" and "innovations 11x" in stop["message"]
    assert "--direction along the handle's tangent" in stop["message"]


def test_the_last_hinge_gives_the_tangent_onwards_while_the_tcp_is_on_its_circle():
    """Issue 50 item 9 (control/last_hinge.py): the tangent at the grasp about the last rotate's hinge, onwards in
    the sense it turned; the configured default once the TCP has left that circle; a result without a usable
    hinge remembers nothing."""
    from tecdard.control.last_hinge import ON_CIRCLE_M, LastHinge
    hinge = np.array([0.157, 0.0, 0.487])
    # the first rotate probed up (+z) from a handle along +x: its result's axis is oriented so that
    # axis x (p_tcp - hinge) = +z there, i.e. -y
    h = LastHinge.from_result("rotate-1", {"hinge": {"p": hinge.tolist(), "axis": [0.0, -2.0, 0.0]}, "radius": 0.15})
    assert h is not None and np.allclose(h.axis, [0.0, -1.0, 0.0])
    assert np.allclose(h.tangent(hinge + [0.15, 0.0, 0.0])[0], [0.0, 0.0, 1.0])
    th = np.radians(30.0)                     # 30 deg later, the handle up at 30 deg: onwards is up and back
    t, why = h.tangent(hinge + 0.15 * np.array([np.cos(th), 0.0, np.sin(th)]) + [0.0, 0.04, 0.0])
    assert np.allclose(t, [-np.sin(th), 0.0, np.cos(th)]) and "rotate-1" in why
    off, why = h.tangent(hinge + [0.15 + 2 * ON_CIRCLE_M, 0.0, 0.0])
    assert off is None and "no longer held on that hinge's circle" in why
    for bad in ({}, {"hinge": None, "radius": 0.1}, {"hinge": {"p": [0, 0], "axis": [0, 1, 0]}, "radius": 0.1},
                {"hinge": {"p": [0, 0, 0], "axis": [0, 0, 0]}, "radius": 0.1},
                {"hinge": {"p": [0, 0, float("nan")], "axis": [0, 1, 0]}, "radius": 0.1},
                {"hinge": {"p": [0, 0, 0], "axis": [0, 1, 0]}, "radius": 0.001}):
        assert LastHinge.from_result("rotate-2", bad) is None, bad


def test_an_idle_contact_ends_after_rest_or_at_once_on_a_fault_and_never_while_moving():
    """Issue 51 item 4 (control/runner.py, end_idle_episode): a contact with no task is released once the TCP and the
    fingertip have rested the configured time, at once on a fault, not while the arm moves or the object turns; a
    task's own contact is never released this way."""
    import types
    from tecdard.control import safety
    from tecdard.control.planner import CartesianPlanner
    from tecdard.control.runner import TaskRunner
    events = []
    runner = TaskRunner(CartesianPlanner(0.02, 0.05, 0.5, 5.0), safety.SafetyLimits(),
                        lambda kind, **f: events.append((kind, f)))
    est = types.SimpleNamespace(onset_t=1.0, angle_rad=0.0, p=np.array([0.3, 0.0, 0.2]))
    still, moving = np.zeros(3), np.array([0.01, 0.0, 0.0])
    episode = runner.directive.episode
    for k in range(60):                            # 1.2 s with the arm moving: never released
        runner.end_idle_episode(1.0 + 0.02 * k, moving, est, rest_s=1.0)
    est.angle_rad = 0.0
    for k in range(60):                            # at rest but the object turning 5 deg/s: never
        est.angle_rad = np.radians(5.0) * 0.02 * k
        runner.end_idle_episode(3.0 + 0.02 * k, still, est, rest_s=1.0)
    assert events == [] and runner.directive.episode == episode
    t = 4.2
    while not events:                              # then at rest (from the last tick it turned): released 1 s on
        runner.end_idle_episode(t, still, est, rest_s=1.0)
        t += 0.02
    assert 5.15 < t < 5.25 and events[0][0] == "contact_released" and events[0][1]["reason"] == "rest", t
    assert runner.directive.episode == episode + 1 and runner.directive.armed
    runner.end_idle_episode(t, still, est, rest_s=1.0)       # that episode's estimate no longer counts
    assert len(events) == 1
    est2 = types.SimpleNamespace(onset_t=t + 1.0, angle_rad=0.0, p=np.zeros(3))
    runner.end_idle_episode(t + 1.1, still, est2, rest_s=1.0, faulted=True)
    assert events[-1][1]["reason"] == "fault" and len(events) == 2
