"""`robot.backend: ros2`: an arm that ROS 2 drives (ros2_control, MoveIt), observed through its joint states.

The daemon reads `sensor_msgs/JointState` from `ros2.joint_states` (the ROS 2 node subscribes and
hands each message here on Zenoh's thread), matches the names to the model's joints, and publishes
the state on its own clock: the header's stamp (system clock) mapped to the daemon's monotonic one.
The TCP comes from the daemon's own kinematics (Pinocchio FK of the model or of the user's URDF); the
fingertip board is read over serial as on any arm. It never commands the arm: task verbs are refused
with `read_only`, `stop` answers and leaves the arm to its driver.

Faults, never a wrong TCP: a stream silent for longer than `robot.ros2.stale_s` (robot_stale), a
state that jumps further than the joints' speed limits allow, out of range or non-finite
(robot_state, robots.state_check), a message lacking a joint of the model, with mismatched array
lengths, duplicated names, an arm's worth of joints none of which is the model's, or a stamp that is
zero or in the future, more joints than any arm has (MAX_JOINTS), or the model's joints from a second
publisher beside the one it started with (robot_joint_states). A message with fewer joints than the
model and none of its (a gripper driver's, on the same topic) is skipped and counted; names the model
does not have beside its own are ignored, as the interface says (the first MAX_EXTRA_NAMES logged).
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from tecdard.options import option, read_options
from tecdard.robots.backend import JointState, RobotBackend, TopicState
from tecdard.robots.ros2_wrench import WrenchTopic
from tecdard.robots.backends import ModelMismatch
from tecdard.robots.state_check import FAULT_HOLD_S

log = logging.getLogger("tecdar.ros2")
DECIMATE_TICKS = 0.5            # joint states closer than this many control ticks are dropped undecoded

STALE_S = 0.1                    # robot.ros2.stale_s: a joint-state stream silent for longer is a fault
FIRST_STATE_S = 3.0              # robot.ros2.first_state_s: at start, joint states this long decide the model's fit
MAX_FUTURE_S = 0.05              # a stamp further ahead of the system clock is refused (clocks not in sync)
MAX_JOINTS = 64                  # a message naming more joints is no arm's (a fault; what it names is not kept)
MAX_EXTRA_NAMES = 64             # names beside the model's remembered (and logged) at most
FAULT = "robot_joint_states"


@dataclass(frozen=True)
class ObserverOptions:
    """The `robot.ros2` section (robot.backend ros2): how the joint states that ROS 2 publishes are judged."""
    stale_s: float = option(STALE_S, "a joint-state stream silent for longer is robot_stale", unit="s", above=0.0,
                            maxval=5.0)
    first_state_s: float = option(FIRST_STATE_S, "at start, joint states this long decide whether the model fits",
                                  unit="s", minval=0.0, maxval=60.0)


class Ros2Observer(RobotBackend):
    name = "ros2"
    commands_arm = False
    read_only_reason = ("robot.backend ros2 observes an arm that ROS 2 drives: tasks are refused; command the arm "
                        "through its own driver")
    sends_home = False                  # an observed arm is never sent home

    def __init__(self, ctx):
        robot = ctx.cfg.section("robot")
        section = robot.section("ros2")
        opts = read_options(ObserverOptions, section)
        self.stale_s, self.first_state_s = opts.stale_s, opts.first_state_s
        self.model_label = "robot.urdf" if robot.has("urdf") else "robot.model"
        self.model = ctx.model
        self.names = list(ctx.model.joint_names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self._check_states(ctx, "ROS 2 joint_states")
        self.state_age_s = self.stale_s
        self._cond = threading.Condition()
        self._latest = JointState(-math.inf, np.array(ctx.q_home, float), np.zeros(len(self.names)), 0)
        self._prev: JointState | None = None
        self._fault: str | None = None
        self._fault_t = -math.inf
        self.skipped = 0                 # messages naming none of the model's joints
        self.commands_dropped = 0
        self.extra_names: set[str] = set()           # at most MAX_EXTRA_NAMES of them
        self.names_seen: list[str] | None = None     # the names of the first message that named none or not all
        # the publisher of the arm's joint states (its GID, from rmw_zenoh's attachment) and when it last sent:
        # a second one beside it is a fault; a new one after it fell silent (a driver's restart) is taken
        self.source: bytes | None = None
        self._source_t = -math.inf
        # decimated to half the control tick (10 ms): a driver at 50-65 Hz (the paper's arm) loses none of its
        # messages to jitter, a 1 kHz one's nine in ten are dropped unread (three quarters of a tick, 15 ms, dropped
        # every other message of a 65 Hz stream)
        tick_s = ctx.cfg.section("control").getfloat("tick_s", 0.02)
        self.wrench = WrenchTopic(ctx.cfg.section("ros2").getstr("base_frame", "base_link", max_len=200), self.stale_s)
        self.topic_state = TopicState("ros2", self.on_joint_state, min_period_s=DECIMATE_TICKS * tick_s,
                                      take_wrench=self.wrench.take)

    # -- lifecycle: the node owns the subscription ------------------------------------------------
    def start(self) -> None:
        """Waits up to first_state_s for a joint state: one that fits is the start; an arm's message that
        does not fit, before any that does, is a model that does not fit the arm (ModelMismatch: exit
        2); none at all is an arm whose driver has not started yet (robot_stale until it does)."""
        log.info("observing the arm through ROS 2 joint states (joints %s; stale after %.0f ms)",
                 ", ".join(self.names), self.stale_s * 1e3)
        t_end = time.monotonic() + self.first_state_s
        with self._cond:
            while self._latest.seq == 0 and self.names_seen is None and time.monotonic() < t_end:
                self._cond.wait(min(0.05, max(0.0, t_end - time.monotonic())))
            names = self.names_seen
            if self._latest.seq > 0:
                return
        if names is not None:
            missing = [n for n in self.names if n not in names]
            raise ModelMismatch(f"{self.model_label}: the joint states name {', '.join(names) or 'no joint'}, and "
                                f"the model's joints are {', '.join(self.names)} (missing: {', '.join(missing)})")
        log.warning("no joint states within %.1f s: robot_stale until the arm's driver publishes them",
                    self.first_state_s)

    def close(self) -> None:
        with self._cond:
            self._cond.notify_all()

    # -- read -------------------------------------------------------------------------------------
    def read_state(self) -> JointState:
        with self._cond:
            return self._latest

    def wait_state(self, seq: int, timeout: float) -> JointState:
        with self._cond:
            if self._latest.seq == seq:
                self._cond.wait(timeout)
            return self._latest

    # -- write: never -----------------------------------------------------------------------------
    def command_joint_velocity(self, qd) -> None:
        """Never sent: no task starts on an observed arm. Were one sent by a bug, it is dropped (counted
        and said once), never raised on the control tick."""
        self.commands_dropped += 1
        if self.commands_dropped == 1:
            log.error("robot.backend ros2 does not command the arm: a joint velocity command was dropped")

    def hold(self) -> None:
        """The arm is ROS 2's: nothing to do (a protective stop here stops the daemon's tasks, of which
        there are none, and says so in its fault)."""

    def faults(self) -> dict[str, str]:
        with self._cond:
            if self._fault is not None and time.monotonic() - self._fault_t >= FAULT_HOLD_S:
                self._fault = None
            return {} if self._fault is None else {FAULT: self._fault}

    # -- the node's handler (Zenoh's thread) ----------------------------------------------------------
    def on_joint_state(self, msg, problem: str | None, source: bytes | None = None) -> None:
        """One JointState message (or why none could be read) from the publisher `source` (its GID; None: it
        did not say): a new state, or a fault naming what is wrong."""
        if msg is not None:
            try:
                problem = self._state(msg, source)
            except Exception as exc:             # a message of the right type with values no arm sends
                problem = f"joint_states: {type(exc).__name__}: {str(exc)[:120]}"
        if problem is not None:
            self._refuse(problem)

    def _state(self, msg, source: bytes | None = None) -> str | None:
        if len(msg.name) > MAX_JOINTS:
            return f"joint_states: {len(msg.name)} joints, more than an arm has (at most {MAX_JOINTS})"
        names = list(msg.name)
        pos, vel = np.asarray(msg.position, float), np.asarray(msg.velocity, float)
        if len(pos) != len(names):
            return f"joint_states: {len(names)} names and {len(pos)} positions"
        if len(vel) not in (0, len(names)):
            return f"joint_states: {len(names)} names and {len(vel)} velocities"
        if len(set(names)) != len(names):
            return "joint_states: a joint is named twice"
        mine = [n for n in names if n in self.index]
        missing = [n for n in self.names if n not in names]
        # an arm's stream that is not the model's: some of its joints, or as many joints as it has but none
        # of them (a gripper's few joints on the same topic are another driver's, not a misfit)
        if self.names_seen is None and ((mine and missing) or (not mine and len(names) >= len(self.names))):
            self.names_seen = names
        if not mine and len(names) < len(self.names):
            self.skipped += 1            # another driver's few joints (a gripper's) on the same topic
            return None
        if not mine:
            return (f"joint_states: {len(names)} joints and none of the model's ({', '.join(names[:3])}, ...; the "
                    f"model's joints: {', '.join(self.names)})")
        if missing:
            return f"joint_states: no {missing[0]} (the model's joints: {', '.join(self.names)})"
        problem = self._one_publisher(source)
        if problem is not None:
            return problem
        extra = set(names) - set(self.names) - self.extra_names
        if extra and len(self.extra_names) < MAX_EXTRA_NAMES:
            extra = set(sorted(extra)[:MAX_EXTRA_NAMES - len(self.extra_names)])
            self.extra_names |= extra
            log.info("joint_states: ignoring joints the model does not have: %s%s", ", ".join(sorted(extra)),
                     " (no more are listed)" if len(self.extra_names) >= MAX_EXTRA_NAMES else "")
        order = [names.index(n) for n in self.names]
        q = pos[order]
        stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        now_wall, now = time.time(), time.monotonic()
        if stamp_s == 0.0:
            return "joint_states: header.stamp is zero (the publisher must stamp its states)"
        if stamp_s > now_wall + MAX_FUTURE_S:
            return (f"joint_states: stamped {stamp_s - now_wall:.3f} s in the future (is this host's clock in sync "
                    "with the publisher's?)")
        t = now - (now_wall - stamp_s)           # the stamp on the daemon's monotonic clock
        prev = self._prev
        if len(vel):
            qd = vel[order]
        elif prev is not None and t > prev.t:
            qd = (q - prev.q) / (t - prev.t)     # no velocities published: from the positions
        else:
            qd = np.zeros(len(self.names))
        with self._cond:
            w = self.wrench.at(t)             # the driver's wrench, where ros2.wrench brings one
            js = JointState(t, q, qd, self._latest.seq + 1) if w is None else \
                JointState(t, q, qd, self._latest.seq + 1, tcp_force=w[0], tcp_torque=w[1], wrench_source="ros2_topic")
            if prev is not None and t <= prev.t:
                return f"joint_states: stamp {stamp_s:.6f} s is not after the previous state's"
            # rates derived from the positions are the jump check's to judge, not the rate check's
            checked = js if len(vel) else JointState(t, q, np.zeros(len(q)), js.seq)
            if not self.state_check.admit(checked):
                return None                      # robot_state holds the fault, naming the reading
            self._prev = js
            self._latest = js
            self._cond.notify_all()
        return None

    def _one_publisher(self, source: bytes | None) -> str | None:
        """Only the publisher the observer started with drives the state; another beside it is a fault (two
        drivers, or a second node echoing the arm), one after it fell silent for stale_s is the driver again."""
        now = time.monotonic()
        if source is None or source == self.source:
            self._source_t = now if source is not None else self._source_t
            return None
        if self.source is not None and now - self._source_t <= self.stale_s:
            return (f"joint_states: a second publisher (GID {source.hex()[:16]}...) beside the arm's "
                    f"({self.source.hex()[:16]}...): only its driver may publish them")
        if self.source is not None:
            log.warning("joint_states: a new publisher (GID %s...) after the last fell silent", source.hex()[:16])
        self.source, self._source_t = source, now
        return None

    def _refuse(self, problem: str) -> None:
        with self._cond:
            if self._fault is None:
                log.warning("%s", problem)
            self._fault, self._fault_t = problem, time.monotonic()
