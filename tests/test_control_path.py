"""The control path's typed pieces: the mode table, the estimator directive, the proprioception ring,
commands under a telemetry flood, a task verb added as one file, and a task's own safety reaction."""
import dataclasses
import json
import textwrap

import numpy as np
import pytest

from tecdard.control import safety
from tecdard.control.modes import Event, Mode, TransitionError, transition
from tecdard.control.pipeline import ContactPipeline
from tecdard.robots.model import READY_Q, ArmModel
from tecdard.api import commands as C
from tecdard import verbs
from tecdard.runtime.control_thread import ControlParams, ControlThread
from tecdard.runtime.main_loop import TELEMETRY_PER_PASS, MainLoop, ZenohDoor, status_json
from tecdard.runtime.intake import QueryIntake
from tecdard.control.pipeline import EstimatorDirective
from tecdard.runtime.messages import DropOldestRing, LatestValue, Outbox, StartTask, Stop
from tecdard.api.session import Keys
from tests.test_control_safety import LaggingArm

FLOOD_STATES = 10_000
TICK_S = 0.02


@pytest.fixture(scope="module")
def model():
    return ArmModel("panda")


# -- the mode table ------------------------------------------------------------------

def test_the_mode_table_allows_the_lifecycle_and_refuses_the_rest():
    m = transition(Mode.IDLE, Event.START)
    assert m is Mode.BUSY and transition(m, Event.END) is Mode.SETTLING
    assert transition(Mode.SETTLING, Event.AT_REST) is Mode.IDLE
    for mode in Mode:
        assert transition(mode, Event.STOP) is Mode.STOPPING      # stop always wins
        assert transition(mode, Event.RESET) is Mode.IDLE
    for mode, event in [(Mode.BUSY, Event.START), (Mode.STOPPING, Event.START), (Mode.IDLE, Event.END),
                        (Mode.IDLE, Event.AT_REST), (Mode.SETTLING, Event.START)]:
        with pytest.raises(TransitionError):
            transition(mode, event)
    assert [m.published(False) for m in Mode] == ["idle", "busy", "busy", "stopped"]
    assert Mode.IDLE.published(True) == "fault" and Mode.BUSY.published(True) == "busy"


# -- the directive ---------------------------------------------------------------------

class RecordingPipeline:
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        return lambda *args: self.calls.append((name, *args))


def test_a_directive_releases_on_a_new_episode_and_applies_only_what_changed():
    pipe = RecordingPipeline()
    d0 = EstimatorDirective()
    d1 = EstimatorDirective(episode=1, armed=False)
    ContactPipeline.follow(pipe, d1, d0)
    assert pipe.calls == [("release",), ("set_trigger_armed", False), ("set_arc_following", False),
                          ("hold_bias", False)]
    pipe.calls.clear()
    ContactPipeline.follow(pipe, EstimatorDirective(episode=1, armed=True), d1)
    assert pipe.calls == [("set_trigger_armed", True)]
    pipe.calls.clear()
    # two episodes begun between two looks of the estimator: one release, the newest begin
    ContactPipeline.follow(pipe, EstimatorDirective(episode=3, begin_t=12.5, bias_held=True), d1)
    assert pipe.calls[:2] == [("release",), ("begin", 12.5)] and ("hold_bias", True) in pipe.calls


def test_the_control_thread_tells_the_estimator_by_state_that_cannot_be_lost(model):
    """The old ("release",) and ("arm", False) tuples were dropped when a queue was full; a directive
    is a value: however many the control thread writes, the estimator reads the newest."""
    directive = LatestValue()
    ct = control_thread(model, directive=directive)
    arm = ct.robot
    ct.submit(StartTask(None, "approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.05,
                                           "stop_angle_deg": 10.0}))
    tick(ct, arm, 1)
    started = directive.get()
    assert started.episode == 1 and started.armed is False       # armed once the approach is steady
    for k in range(2, 41):
        tick(ct, arm, k)
    assert directive.get().armed is True and directive.get().episode == 1
    ct.request_stop(Stop(None))
    tick(ct, arm, 41)
    ended = directive.get()
    # the trigger stays disarmed while the arm brakes (issue 34: the stop is no contact), and arms at rest
    assert ended.episode == 2 and ended.armed is False and not ended.arc_following and not ended.bias_held
    for k in range(42, 200):
        tick(ct, arm, k)
        if directive.get().armed:
            break
    assert directive.get().armed is True and directive.get().episode == 2


def test_the_proprioception_ring_overwrites_the_oldest_and_counts():
    ring = DropOldestRing(4)
    for i in range(6):
        ring.push(i)
    assert ring.drain() == [2, 3, 4, 5] and ring.overwritten == 2 and ring.drain() == []


# -- commands under a telemetry flood --------------------------------------------------

class FakeQuery:
    """What QueryIntake uses of a zenoh.Query: its key expression, its payload, and reply()."""

    def __init__(self, key: str, payload: dict | None = None, delivered: list | None = None):
        self.key_expr = key
        self.payload = None if payload is None else json.dumps(payload).encode()
        self.replies = []
        self.delivered = delivered if delivered is not None else []     # every query's replies, in order

    def reply(self, key, text, encoding=None):
        self.replies.append(json.loads(text))
        self.delivered.append(self)


class Publisher:
    def __init__(self):
        self.n = 0

    def put(self, _text):
        self.n += 1


class FreshRing:
    total, last_t, overwritten = 1, 0.0, 0


def control_thread(model, directive=None):
    ct = ControlThread(ControlParams(tick_s=TICK_S), model, robot=None, ring=FreshRing(), contact=LatestValue(),
                       directive=directive or LatestValue(), outbox=Outbox(FLOOD_STATES * 2), q_home=READY_Q["panda"],
                       robot_name="sim")
    ct.robot = LaggingArm(np.array(READY_Q["panda"], float), iter(lambda: 0.0, None))
    return ct


def tick(ct, arm, k: int) -> None:
    now = TICK_S * k
    arm.advance(now)
    FreshRing.last_t = now
    ct.tick(now)


def test_no_command_is_lost_or_reordered_and_stop_is_answered_within_one_tick_under_a_telemetry_flood(model):
    keys = Keys("sim")
    ct = control_thread(model)
    intake = QueryIntake(keys, C.Limits(), ct, lambda: status_json(ct))
    main = MainLoop(intake, ct, ct.outbox, (ZenohDoor(intake, Publisher(), Publisher(), Publisher()),))
    rotate = FakeQuery(keys.cmd("rotate"), {"angle_deg": 10.0})
    intake.handle(rotate, keys.cmd("rotate"), rotate.payload, 0.0)
    tick(ct, ct.robot, 1)
    main.serve_commands(0.02)
    assert rotate.replies[0]["ok"] is True
    task = rotate.replies[0]["task"]
    for _ in range(FLOOD_STATES):          # the telemetry of a stalled main thread, ahead of everything below
        ct.outbox.put("state", {"t": 0.0, "seq": 0})
    delivered = []
    sent = [FakeQuery(keys.cmd("cancel"), {"task": "rotate-0000"}, delivered),  # not the running task: no_task
            FakeQuery(keys.cmd("probe"), {}, delivered),                        # busy: the rotate runs
            FakeQuery(keys.cmd("cancel"), {"task": task}, delivered),           # cancels the rotate
            FakeQuery(keys.cmd("point"), {}, delivered)]                        # busy: the rotate is braking
    for q in sent:
        intake.handle(q, str(q.key_expr), q.payload, 0.02)
    tick(ct, ct.robot, 2)
    main.serve_commands(0.04)
    assert [len(q.replies) for q in sent] == [1, 1, 1, 1] and delivered == sent     # none lost, none reordered
    assert [q.replies[0].get("error", {}).get("code", "ok") for q in sent] == ["no_task", "busy", "ok", "busy"]
    for k in range(3, 60):                  # the cancelled rotate brakes to rest
        tick(ct, ct.robot, k)
        if ct.runner.mode is Mode.IDLE:
            break
    assert ct.runner.mode is Mode.IDLE
    main.serve_commands(TICK_S * k)
    # at rest, with 10 000 state messages still queued: a stop is answered after one tick and one pass
    stop = FakeQuery(keys.cmd("stop"))
    intake.on_stop(stop)
    tick(ct, ct.robot, k + 1)
    main.serve_commands(TICK_S * (k + 1))
    assert stop.replies == [{"ok": True}]
    # and `status` says what the control loop knows now, not what waits in the telemetry queue
    status = FakeQuery(keys.cmd("status"))
    intake.handle(status, keys.cmd("status"), None, TICK_S * (k + 1))
    state = status.replies[0]["state"]
    assert state["seq"] == k + 1 and state["mode"] == "idle" and state["task"] is None
    assert main.publish_telemetry(0.0) == TELEMETRY_PER_PASS
    assert ct.outbox.qsize() >= FLOOD_STATES - TELEMETRY_PER_PASS     # the flood is still there


def test_the_estimator_is_told_when_the_daemon_rests_and_when_a_task_starts(model):
    """Issue 37: at rest the estimator thread waits for longer batches and the arm's link sends fewer
    states; a task's start is said at once to both, an observed arm's estimator never rests, and a
    start cuts a rest batch's wait short."""
    import threading
    import time
    import types
    from tecdard.drivers.ring import SampleRing
    from tecdard.runtime.workers import IDLE_BATCH_FACTOR, REST_BATCH_FACTOR, EstimatorThread

    class Told:
        saturated_since = None

        def __init__(self):
            self.said = []
            self.ticks = []

        def set_resting(self, resting):
            self.said.append(resting)

        def note_command(self, t, qd):
            self.ticks.append((t, np.array(qd)))

    keys = Keys("sim")
    ct = control_thread(model)
    ct.estimator = told = Told()
    robot_told = []
    ct.robot.set_resting = robot_told.append                      # the arm's link paces its states at rest
    intake = QueryIntake(keys, C.Limits(), ct, lambda: status_json(ct))
    main = MainLoop(intake, ct, ct.outbox, (ZenohDoor(intake, Publisher(), Publisher(), Publisher()),))
    tick(ct, ct.robot, 1)
    tick(ct, ct.robot, 2)
    assert told.said == [True]                                    # idle: said once, not every tick
    rotate = FakeQuery(keys.cmd("rotate"), {"angle_deg": 10.0})
    intake.handle(rotate, keys.cmd("rotate"), rotate.payload, 0.04)
    tick(ct, ct.robot, 3)
    main.serve_commands(0.06)
    assert rotate.replies[0]["ok"] is True and told.said == [True, False]     # the tick that started it
    ct.runner.cancel(None)
    for k in range(4, 60):
        tick(ct, ct.robot, k)
        if ct.runner.mode is Mode.IDLE:
            break
    assert told.said == [True, False, True]                       # at rest again once the arm has braked
    assert robot_told == told.said
    # every tick's command reaches the estimator too (the onset trigger's word on the arm's own steps)
    assert len(told.ticks) == k and [t for t, _ in told.ticks] == sorted(t for t, _ in told.ticks)
    assert any(np.abs(qd).sum() > 0 for _, qd in told.ticks) and not np.abs(told.ticks[0][1]).any()

    # the estimator thread's side: a rest batch's wait ends at a task's batch when the task starts
    ring = SampleRing(4096)
    pipe = types.SimpleNamespace(params=types.SimpleNamespace(output_period_s=0.005),    # what the thread reads
                                 cond=types.SimpleNamespace(R_tcp_imu=np.eye(3)))
    est = EstimatorThread(pipe, ring, LatestValue(), Outbox(4), min_batch=33)
    est.set_resting(True)
    assert est.resting.is_set()
    got = []
    waiting = threading.Thread(target=lambda: got.append(ring.pop(4096, 5.0, REST_BATCH_FACTOR * 33)))
    waiting.start()
    ring.push(np.arange(70.0), np.zeros((70, 3)), np.zeros((70, 3)))   # a task's batch (66) is there, a rest one not
    time.sleep(0.05)
    assert not got
    est.set_resting(False)
    waiting.join(5.0)
    assert len(got) == 1 and len(got[0]) == 70 and IDLE_BATCH_FACTOR * 33 <= 70 and not est.resting.is_set()
    observer = EstimatorThread(pipe, SampleRing(64), LatestValue(), Outbox(4), min_batch=33, rests=False)
    observer.set_resting(True)
    assert not observer.resting.is_set()


# -- a task verb is one file ----------------------------------------------------------------

WIGGLE = '''
    """`wiggle`: lift the TCP by `distance` and come to rest (a verb defined by this file alone)."""
    import enum

    import numpy as np

    from tecdard.control.safety import StopCause
    from tecdard.control.tasks import Motion, Task
    from tecdard.verbs import Field, TaskVerb


    class WiggleTask(Task):
        class Phase(enum.StrEnum):
            LIFT = "lift"

        kind = "wiggle"

        def __init__(self, task_id, distance, speed, max_force_n):
            super().__init__(task_id, np.array([0.0, 0.0, 1.0]), speed)
            self.distance = distance
            self.reactions = (self._pushed,)
            self.max_force_n = max_force_n

        def _pushed(self, inp):
            if inp.contact_force is not None and np.linalg.norm(inp.contact_force) > self.max_force_n:
                return StopCause("wiggle_force", "pushed while wiggling")
            return None

        def _started(self, inp):
            self._enter(self.Phase.LIFT, inp.t)

        def _step_lift(self, inp):
            target = self.p_start + self.direction * self.distance
            if inp.planner_at_rest and np.linalg.norm(inp.p_ref - target) < 1e-4:
                self._done({"lifted_m": float(inp.p[2] - self.p_start[2])})
                return None
            return Motion(target, np.zeros(3), self.R_hold)

        STEPS = {Phase.LIFT: _step_lift}


    def build(f, ctx):
        return WiggleTask(ctx.task_id, f["distance"], f["speed"], f["max_force_n"])


    VERB = TaskVerb("wiggle", "lift a little", (
        Field("distance", "number", 0.003, 0.001, 0.01, "m", "lift"),
        Field("speed", "number", lambda lim: lim.default_speed, lambda lim: lim.min_speed,
              lambda lim: lim.max_speed, "m/s"),
        Field("max_force_n", "number", 5.0, 0.1, 50.0, "N"),
    ), build)
'''


@pytest.fixture
def wiggle_verb(tmp_path):
    (tmp_path / "wiggle.py").write_text(textwrap.dedent(WIGGLE))
    verbs.__path__.append(str(tmp_path))
    try:
        yield
    finally:
        verbs.__path__.remove(str(tmp_path))
        verbs.REGISTRY.pop("wiggle", None)
        verbs._discovered.discard("wiggle")


def test_a_new_task_verb_is_one_file(model, wiggle_verb):
    from tecdard.cli import task_verbs as client_cli
    assert "wiggle" in C.task_verbs() and "wiggle" in C.verbs()
    fields = C.validate("wiggle", {}, C.Limits())
    assert fields == {"distance": 0.003, "speed": 0.02, "max_force_n": 5.0}
    with pytest.raises(C.CommandError) as exc:
        C.validate("wiggle", {"distance": 0.5}, C.Limits())
    assert exc.value.code == C.OUT_OF_LIMITS and exc.value.message.startswith("distance:")
    assert [opt for opt, *_ in client_cli.verb_options()["wiggle"]] == ["--distance", "--speed", "--max-force-n"]
    keys = Keys("sim")
    ct = control_thread(model)
    intake = QueryIntake(keys, C.Limits(), ct, lambda: None)
    q = FakeQuery(keys.cmd("wiggle"), {"distance": 0.004})
    intake.handle(q, keys.cmd("wiggle"), q.payload, 0.0)
    for k in range(1, 200):
        tick(ct, ct.robot, k)
        if ct.runner.mode is Mode.IDLE and k > 1:
            break
    events = [m[1] for m in list(ct.outbox.queue) if m[0] == "event"]
    (done,) = [e for e in events if e["kind"] == "task_done"]
    assert done["verb"] == "wiggle" and done["result"]["lifted_m"] == pytest.approx(0.004, abs=2e-4)


def test_a_tasks_own_reaction_is_a_protective_stop(model, wiggle_verb):
    ct = control_thread(model)
    ct.submit(StartTask(None, "wiggle", C.validate("wiggle", {}, C.Limits())))
    tick(ct, ct.robot, 1)
    assert ct.runner.mode is Mode.BUSY
    pushed = dataclasses.replace(ct.robot.read_state(), tcp_force=np.array([0.0, 0.0, 8.0]))   # under 15 N
    ct.runner.check(pushed.tcp_force, None)
    stops = [m[1] for m in list(ct.outbox.queue) if m[0] == "event" and m[1]["kind"] == "protective_stop"]
    assert [s["cause"] for s in stops] == ["wiggle_force"] and ct.runner.mode is Mode.STOPPING
    # the generic force limit (15 N) comes first; the reactions after it
    reactions = (lambda inp: safety.StopCause("x", "y"),)
    limits = safety.SafetyLimits()
    assert safety.check_task(safety.SafetyInput(np.array([0.0, 0.0, 20.0]), None, None), limits, reactions).cause == "force"
    assert safety.check_task(safety.SafetyInput(None, None, None), limits, reactions).cause == "x"


# -- an estimator is one file ----------------------------------------------------------------

TOOL_TIP = '''
    """`tool-tip`: the contact is where the tool model puts the tip at onset (a floor for any other).
    Its option, `estimator.tool_tip.tip_in_tcp`, is its own; so is its input, the TCP's orientation."""
    from dataclasses import dataclass

    import numpy as np

    from tecdard.control.estimators.base import ContactEstimator, EstimatorSpec


    @dataclass
    class ToolTipOptions:
        tip_in_tcp: tuple = (0.0, 0.0, 0.1)     # m, TCP frame
        std_m: float = 0.05

        @classmethod
        def from_config(cls, section):
            return cls(tuple(section.getvec3("tip_in_tcp", [0.0, 0.0, 0.1])),
                       section.getfloat("std_m", 0.05, above=0.0, maxval=1.0))


    class ToolTip(ContactEstimator):
        method = "tool-tip"

        def __init__(self, options, plane):
            self.options, self.p_c = options, None

        def start(self, p_g, v_g):
            self.p_c, self.steps = None, 0

        def update(self, samples):
            if self.p_c is None and len(samples):
                self.p_c = samples.p[0] + samples.R[0] @ np.array(self.options.tip_in_tcp)
            self.steps += len(samples)

        def report(self):
            cov = np.eye(3) * self.options.std_m ** 2
            return self.p_c.copy(), cov, cov


    ESTIMATORS = (EstimatorSpec("tool-tip", "the tool model's tip at onset",
                                lambda options, plane: ToolTip(options, plane), "tool_tip", ToolTipOptions),)
'''


@pytest.mark.slow
def test_a_new_estimator_with_its_own_option_and_input_is_one_file(tmp_path):
    from tecdard.config import Config, ConfigError
    from tecdard.control import estimators
    from tests.test_pipeline import simulate
    (tmp_path / "tool_tip.py").write_text(textwrap.dedent(TOOL_TIP))
    estimators.__path__.append(str(tmp_path))
    try:
        assert "tool-tip" in estimators.names() and estimators.names()[0] == "ekf"
        cfg = Config({"estimator": {"method": "tool-tip", "tool_tip": {"tip_in_tcp": [-0.15, 0.0, 0.0]}}})
        pipe = ContactPipeline.from_config(cfg.section("estimator"), np.eye(3))
        cfg.check_unused()                                   # its section was read, by its module
        assert pipe.method == "tool-tip" and pipe.estimator.options.tip_in_tcp == (-0.15, 0.0, 0.0)
        options = estimators.read_options(cfg.section("estimator"))
        _, est, center, axis, _, _ = simulate(np.eye(3), method="tool-tip", options=options)
        assert est.method == "tool-tip" and est.nis_ratio is None
        # the hinge, 15 cm along the TCP's x (its orientation at onset turns the option into the world)
        assert np.linalg.norm(est.p - center) < 1e-3
        typo = Config({"estimator": {"tool_tip": {"tip_in_tcpp": [0.0, 0.0, 0.1]}}})
        ContactPipeline.from_config(typo.section("estimator"), np.eye(3))
        with pytest.raises(ConfigError, match="estimator.tool_tip.tip_in_tcpp: unknown option"):
            typo.check_unused()
    finally:
        estimators.__path__.remove(str(tmp_path))
        estimators.REGISTRY.pop("tool-tip", None)
        estimators._discovered.discard("tool_tip")


def test_the_sensor_watch_holds_a_fault_while_its_condition_lasts():
    watch = safety.SensorWatch(safety.SafetyLimits(imu_stale_s=0.05), t_boot=0.0)
    assert watch.update(0.5, 0, float("-inf"), 0.0, None) == []              # the first samples are on their way
    (change,) = watch.update(1.2, 0, float("-inf"), 0.0, None)
    assert change[:2] == ("fault", "imu_stale") and "since the start" in change[2]
    assert watch.update(1.3, 10, 1.29, 0.0, None) == [("fault_cleared", "imu_stale", change[2])]
    # clipped at full scale for longer than imu_stale_s: a fault, held while the clipping goes on
    assert watch.update(1.32, 20, 1.31, 0.0, 1.30) == []
    (sat,) = watch.update(1.40, 30, 1.39, 0.0, 1.30)
    assert sat[:2] == ("fault", "imu_saturated") and watch.faults == {"imu_saturated": sat[2]}
    assert watch.update(1.41, 31, 1.40, 0.0, 1.405) == []                    # clipped again: still held
    assert [c[:2] for c in watch.update(1.42, 32, 1.41, 0.0, None)] == [("fault_cleared", "imu_saturated")]


def test_a_robot_fault_stops_the_plan_where_the_controller_stopped_the_arm(model, wiggle_verb):
    """The robot's own controller has stopped the arm (its protective stop): the daemon commands no
    brake that runs on past it. Such commands are refused now, or left in the controller's command
    registers to run when its program starts again. An IMU fault, with the arm still ours, brakes."""
    ct = control_thread(model)
    ct.submit(StartTask(None, "wiggle", C.validate("wiggle", {"distance": 0.01}, C.Limits())))
    for k in range(1, 12):
        tick(ct, ct.robot, k)
    assert ct.runner.mode is Mode.BUSY and np.linalg.norm(ct.runner.planner.velocity) > 1e-3   # moving
    ct.robot.faults = lambda: {"robot_protective_stop": "the controller reports a protective stop"}
    ct.robot.qd[:] = 0.0                               # the controller has halted the arm
    p_halted = model.fk(ct.robot.q).translation.copy()
    tick(ct, ct.robot, 12)
    events = [m[1]["kind"] for m in list(ct.outbox.queue) if m[0] == "event"]
    assert "protective_stop" in events and "task_failed" in events
    for k in range(13, 17):
        tick(ct, ct.robot, k)
        assert np.linalg.norm(model.fk(ct.robot.q).translation - p_halted) < 1e-4
    assert ct.runner.mode is Mode.IDLE and np.all(ct.robot.qd == 0.0)
