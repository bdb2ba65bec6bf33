"""A controller's readings are input too: a state that lies never moves the arm.

Two tiers:
- every backend's link (UR, Franka, the simulator) fed the states its child would send, with the
  lies (NaN, out of range, a jump, late, frozen), and the control thread ticked on the backend:
  each lie is a fault and a protective stop, and no command is taken from the state that lied;
- the whole daemon against the fake UR controller, through the real ur-rtde client: the red
  team's reproductions (the shoulder reported at 7 rad, the elbow at 6.5 rad, NaN readings, every
  state 0.4 s late, a frozen state) during an approach at 1 cm/s.
"""
import time

import numpy as np
import pytest

from tecdard.config import Config
from tecdard.control.modes import Mode
from tecdard.robots import backends
from tecdard.robots.model import READY_Q, ArmModel
from tecdard.robots.state_check import FAULT_HOLD_S, StateCheck
from tecdard.runtime.control_thread import ControlParams, ControlThread
from tecdard.runtime.messages import LatestValue, Outbox, StartTask
from tests.conftest import daemon_config
from tests.test_control_safety import drained_events as events

TICK_S = 0.02
APPROACH_RATE_BOUND = 0.1     # rad/s: the approach asks ~0.03 rad/s; the lies asked up to 3.14 rad/s
APPROACH = {"direction": [0.0, 0.0, -1.0], "speed": 0.01, "max_distance": 0.05, "stop_angle_deg": 10.0}


# -- every backend's link, fed what its child would send ---------------------------------------

class Feed:
    """A backend built from its config but never started: its link takes the messages its child
    would send (`state(t, q, qd, ...)` builds one in the child's own format), and records the
    commands the daemon gives (`commands`: ("qd", rates) or ("hold",))."""

    def __init__(self, name: str):
        self.name = name
        model_name = {"ur": "ur5", "franka": "fr3", "sim": "panda"}[name]
        self.model = ArmModel(model_name)
        self.q0 = np.array(READY_Q[model_name], float)
        cfg = daemon_config(**{"robot.backend": name, "robot.model": model_name, "robot.q_home": list(self.q0),
                               "robot.ur": {"host": "127.0.0.1"}, "robot.franka": {"host": "127.0.0.1"}})
        self.backend = backends.build(name, backends.BackendContext(Config(cfg), self.model, self.q0, [0, 0, 0, 1]))
        self.link = self.backend.process if name == "sim" else self.backend.link
        self.commands: list = []
        self.link.command_joint_velocity = lambda qd: self.commands.append(("qd", np.array(qd)))
        self.link.hold = lambda: self.commands.append(("hold",))
        self.pending: list = []             # states on their way: (arrival, measured, q, qd, pose_nan)

    def send(self, t_host: float, q, qd=None, lateness_s: float = 0.0, pose_nan: bool = False) -> None:
        """A state measured at `t_host` (our clock), arriving `lateness_s` later (`flush` hands on
        those that have arrived by then)."""
        qd = np.zeros(len(q)) if qd is None else np.asarray(qd, float)
        q = np.asarray(q, float)
        if lateness_s > 0:
            self.pending.append((t_host + lateness_s, t_host, q, qd, pose_nan))
            return
        self._deliver(t_host, t_host, q, qd, pose_nan)

    def flush(self, now: float) -> None:
        while self.pending and self.pending[0][0] <= now:
            self._deliver(*self.pending.pop(0))

    def _deliver(self, rx_t: float, t_host: float, q, qd, pose_nan: bool) -> None:
        lateness_s = rx_t - t_host
        if self.name == "ur":
            from tecdard.robots.ur_link import UrState
            pose = list(self.model.fk(np.nan_to_num(q)).translation) + [0.0, np.pi, 0.0]
            if pose_nan:
                pose[0] = float("nan")
            self.link._handle(("state", UrState(t_host - 1000.0, t_host + lateness_s, tuple(q), tuple(qd),
                                                tuple(pose), (0.0,) * 6, (0.0,) * 6, 7, 1, 1, True)))
        elif self.name == "franka":
            from tecdard.robots.franka_link import STATE_FLOATS
            a = np.zeros(STATE_FLOATS)             # t, rx_t, q, dq, O_T_EE, f_ext (6), grip width, grasped
            a[0], a[1], a[2:9], a[9:16] = t_host - 1000.0, t_host + lateness_s, q, qd
            a[16:32] = np.eye(4).ravel()
            a[38:40] = np.nan
            if pose_nan:
                a[32] = np.nan            # the force the child computed from the torques
            self.link._handle(("state", a))
        else:
            from tecdard.robots.backend import JointState
            self.link._seq = getattr(self.link, "_seq", 0) + 1
            js = JointState(t=t_host, q=q, qd=qd, seq=self.link._seq,
                            tcp_force=np.array([np.nan if pose_nan else 0.0, 0.0, 0.0]))
            self.link._handle(("state", js, None))


class Ring:
    total, last_t, overwritten = 1, 0.0, 0


def control_on(feed: Feed) -> ControlThread:
    ct = ControlThread(ControlParams(tick_s=TICK_S, workspace_min=(-2.0, -2.0, -1.0), workspace_max=(2.0, 2.0, 2.0),
                                     imu_stale_s=1e9),
                       feed.model, robot=feed.backend, ring=Ring(), contact=LatestValue(), directive=LatestValue(),
                       outbox=Outbox(4096), q_home=feed.q0, robot_name="lies")
    return ct


def run_approach(feed: Feed, lie, ticks: int = 60, lie_at: int = 20):
    """An approach at 1 cm/s on the backend, its states sent at 2 ms until `lie_at` ticks, then
    what `lie(feed, t, q)` sends; returns the control thread, and the commands taken after the lie."""
    ct = control_on(feed)
    t0 = time.monotonic()
    q = feed.q0.copy()
    feed.send(t0, q)
    ct.submit(StartTask(None, "approach", dict(APPROACH)))
    after = None
    for k in range(1, ticks):
        now = t0 + k * TICK_S
        qd = feed.commands[-1][1] if feed.commands and feed.commands[-1][0] == "qd" else np.zeros(len(q))
        for i in range(10):                 # the controller's states in this tick, 2 ms apart
            t = now - TICK_S + (i + 1) * 0.002
            q = q + qd * 0.002
            if k < lie_at:
                feed.send(t, q, qd)
            else:
                lie(feed, t, q, qd)
        feed.flush(now)
        Ring.last_t = now
        if k == lie_at:
            after = len(feed.commands)
        ct.tick(now)
    return ct, feed.commands[after:]


LIES = {
    # what the controller sends instead of the truth, and the fault it must be
    "shoulder at 7 rad": (lambda f, t, q, qd: f.send(t, np.r_[q[:1], 7.0, q[2:]], qd), "robot_state"),
    "elbow at 6.5 rad": (lambda f, t, q, qd: f.send(t, np.r_[q[:2], 6.5, q[3:]], qd), "robot_state"),
    "a NaN joint": (lambda f, t, q, qd: f.send(t, np.r_[q[:1], np.nan, q[2:]], qd), "robot_state"),
    "a NaN rate": (lambda f, t, q, qd: f.send(t, q, np.r_[np.nan, qd[1:]]), "robot_state"),
    "a NaN TCP reading": (lambda f, t, q, qd: f.send(t, q, qd, pose_nan=True), "robot_state"),
    "a joint that jumps 0.2 rad": (lambda f, t, q, qd: f.send(t, np.r_[q[:3], q[3] + 0.2, q[4:]], qd),
                                   "robot_state"),
    "states 0.4 s late": (lambda f, t, q, qd: f.send(t, q, qd, lateness_s=0.4), "robot_stale"),
    "a frozen state": (lambda f, t, q, qd: None, "robot_stale"),
}


@pytest.mark.parametrize("backend", ["ur", "franka", "sim"])
@pytest.mark.parametrize("lie", list(LIES))
def test_every_backends_lying_state_is_a_fault_and_never_commands_the_arm(backend, lie):
    if backend == "ur":
        pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    send, code = LIES[lie]
    feed = Feed(backend)
    ct, after = run_approach(feed, send)
    faults = events(ct, "fault", "protective_stop", "task_failed")
    raised = [e for e in faults if e["kind"] == "fault"]
    assert raised and raised[0]["code"] == code, faults
    stop = next(e for e in faults if e["kind"] == "protective_stop")
    assert stop["cause"] == code
    if code == "robot_state":
        assert feed.backend.state_check.refused > 0
        assert feed.name == "sim" or feed.backend.settings.host in raised[0]["message"]
    # nothing the lie said reached the servo: from the lie on, the arm is held, or driven near the
    # approach's own rate (0.03 rad/s) from a state that passed and is younger than the budget
    rates = [np.abs(c[1]).max() for c in after if c[0] == "qd"]
    assert max(rates, default=0.0) < APPROACH_RATE_BOUND, rates
    assert ct.runner.task is None and ct.runner.mode is not Mode.BUSY


def test_a_state_that_lies_names_the_reading(backend="ur"):
    pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    feed = Feed(backend)
    t = time.monotonic()
    feed.send(t, feed.q0)
    feed.send(t + 0.002, np.r_[feed.q0[:1], 7.0, feed.q0[2:]])
    fault = feed.backend.state_faults()["robot_state"]
    assert fault.startswith("UR controller 127.0.0.1: state refused: shoulder_lift_joint at 7.000 rad, outside its "
                            "range [-6.283, 6.283] rad"), fault
    feed.send(t + 0.004, np.r_[feed.q0[:1], np.nan, feed.q0[2:]])
    assert "shoulder_lift_joint position reads nan rad" in feed.backend.state_faults()["robot_state"]
    # the states that lied were never published: the newest is the last true one
    assert feed.backend.read_state().t == pytest.approx(t, abs=1e-3)


def test_the_state_fault_holds_until_states_have_passed_for_a_while():
    model = ArmModel("panda")
    now = [0.0]
    check = StateCheck(model, "arm", clock=lambda: now[0])
    from tecdard.robots.backend import JointState
    q = np.array(READY_Q["panda"])
    assert check.admit(JointState(0.0, q, np.zeros(7)))
    now[0] = 0.01
    assert not check.admit(JointState(0.01, q + 1.0, np.zeros(7)))            # 1 rad in 10 ms
    assert "jumped" in check.fault
    for k in range(2, 60):
        now[0] = 0.01 * k
        assert check.admit(JointState(now[0], q, np.zeros(7)))
        assert (check.fault is None) == (now[0] - 0.01 >= FAULT_HOLD_S)
    # a joint that really moves at its limit is no jump
    check.reset()
    qd = model.qd_max.copy()
    assert all(check.admit(JointState(0.002 * k, q + qd * 0.002 * k * 0.01, qd)) for k in range(10))


def test_a_stale_state_holds_the_servo_even_before_the_fault_is_judged():
    """A tick that started late defers the stale fault by one tick (the daemon's own stall), but
    never servos from the stale state meanwhile."""
    feed = Feed("sim")
    ct = control_on(feed)
    t0 = time.monotonic()
    feed.send(t0, feed.q0)
    ct.submit(StartTask(None, "approach", dict(APPROACH)))
    ct.tick(t0 + 0.001)
    assert feed.commands[-1][0] == "qd"
    ct._late_s = 0.05
    ct.tick(t0 + 0.3)                     # the state is 300 ms old and the tick late: judged next tick
    assert feed.commands[-1] == ("hold",) and "robot_stale" not in ct.faults
    ct._late_s = 0.0
    ct.tick(t0 + 0.32)
    assert "robot_stale" in ct.faults and ct.runner.task is None


def test_no_non_finite_number_is_ever_published():
    """JSON has no NaN or Infinity: the wire's encoder never writes them (a strict parser would
    refuse the whole message), and a NaN reading is a fault before it gets that far."""
    import json

    from tecdard.api.session import dumps

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in {text}"))

    assert strict(dumps({"tcp": {"p": [0.1, float("nan"), float("inf")]}, "x": np.float64(-np.inf)})) == \
        {"tcp": {"p": [0.1, None, None]}, "x": None}
    feed = Feed("sim")
    ct, _ = run_approach(feed, LIES["a NaN TCP reading"][0])
    states = []
    while not ct.outbox.empty():
        kind, *rest = ct.outbox.get_nowait()
        states += [rest[0]] if kind == "state" else []
    assert states and all(strict(dumps(s)) for s in states)
    assert states[-1]["faults"] and states[-1]["mode"] != "idle"


def test_a_state_whose_sums_overflow_is_judged_reading_by_reading():
    """Issue 37: each check is first made whole (one sum says whether every value is finite); values
    that are finite but whose sum overflows are then looked at one by one, so that the verdict and
    its message are those of the reading itself: a rate over its limit, a TCP out of reach."""
    from tecdard.robots.backend import JointState
    model = ArmModel("panda")
    check = StateCheck(model, "arm")
    q = np.array(READY_Q["panda"])
    huge = np.full(7, 1e308)
    assert "rate" in check.problem(JointState(0.0, q, huge)) and "over" in check.problem(JointState(0.0, q, huge))
    pose = np.eye(4)
    pose[:3, 3] = 1e308
    assert "from the base" in check.problem(JointState(0.0, q, np.zeros(7), tcp_pose=pose))
    pose[:3, 3] = [0.3, 0.0, 0.5]
    assert check.problem(JointState(0.0, q, np.zeros(7), tcp_pose=pose, tcp_force=np.full(3, 1e308))) is None
    pose[0, 0] = np.nan
    assert "rotation" in check.problem(JointState(0.0, q, np.zeros(7), tcp_pose=pose))
    pose[0, 0], pose[1, 3] = 1.0, np.inf
    assert "TCP position reads" in check.problem(JointState(0.0, q, np.zeros(7), tcp_pose=pose))
