"""Simulated robot backend: 1 kHz joint integration in a physics thread, with a world and a fingertip IMU."""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from tecdard.options import option, read_options
from tecdard.robots.backend import JointState, joint_rates
from tecdard.robots.model import ArmModel
from tecdard.sim.world import SimTruth

log = logging.getLogger("tecdar.sim")

PHYSICS_RATE_HZ = 1000.0
# The physics integrates in slices of this length. Each slice has a fixed cost (the IMU synthesis
# of its samples, some fifty numpy calls, the truth and the bookkeeping) of about 1 ms on a shared
# 2-core machine: short slices spend most of the simulation's CPU on that, and a loaded machine
# then lets the physics fall behind real time. Commands and proprioception keep their own stamps,
# so a longer slice delays only when a state or an IMU chunk is handed on (by at most one slice),
# not what it says. docs/simulator.md has the costs measured.
PHYSICS_WAKE_S = 0.01
STATE_BACKLOG = 256        # proprioception samples kept for `drain_states` between two drains


@dataclass
class SimRobotParams:
    """The `sim.robot` section: the simulated arm's controller."""
    q_home: np.ndarray                 # rad, robot.q_home (given)
    proprio_rate_hz: float = option(65.0, "the controller's state rate (the paper's robot's)", unit="Hz",
                                    minval=10.0, maxval=PHYSICS_RATE_HZ)
    command_latency_s: float = option(0.002, "a joint command takes effect this late", unit="s", minval=0.0,
                                      maxval=0.1)
    tracking_tau_s: float = option(0.01, "the joints follow their commanded rates with this time constant",
                                   unit="s", minval=0.0, maxval=0.5)
    encoder_noise_rad: float = option(5e-5, "the joint encoders' noise", unit="rad", minval=0.0)
    tcp_speed_noise: float = option(2e-4, "noise of the reported TCP velocity", unit="m/s", minval=0.0)
    command_timeout_s: float = option(0.1, "no joint command for this long: the arm stops by itself (0: never)",
                                      unit="s", minval=0.0, maxval=10.0)
    protective_stop_force_n: float = option(150.0, "the simulated controller's protective stop: a force at the TCP "
                                                   "beyond this halts the arm until `recover` (a UR's default limit)",
                                            unit="N", above=0.0, maxval=10000.0)

    @classmethod
    def from_config(cls, section, q_home: np.ndarray) -> "SimRobotParams":
        return read_options(cls, section, q_home=np.array(q_home, dtype=float))


class SimRobot:
    """A velocity-commanded arm. Implements RobotReceive and RobotControl.

    The physics thread owns the joint state, the world and the IMU signal; the
    daemon's threads see only the latest proprioception (published at
    `proprio_rate_hz` with encoder noise) and hand in joint velocity commands,
    which take effect after `command_latency_s` through a first-order tracking
    lag of `tracking_tau_s`. Like a real arm's velocity interface, it stops by itself
    when commands cease for `command_timeout_s` (a stalled controller must not leave it
    moving); `watchdog_stops` counts those.
    """

    def __init__(self, model: ArmModel, params: SimRobotParams, world_factory=None, imu=None, seed: int = 0,
                 clock=time.monotonic):
        """`clock` is the time source (monotonic by default). For as-fast-as-possible runs pass a
        manual clock and call `advance_to()` yourself instead of `start()`."""
        self.clock = clock
        self.model = model.clone()
        self.p = params
        self.imu = imu
        self.rng = np.random.default_rng(seed + 1)
        self.q = params.q_home.copy()
        self.qd = np.zeros(model.nq)
        self.t = clock()
        oMtcp, twist = self.model.fk_twist(self.q, self.qd)
        self._world_factory = world_factory
        self.world = world_factory(oMtcp.translation.copy(), oMtcp.rotation.copy()) if world_factory else None
        self._v_prev = twist[:3].copy()
        self._cmds: collections.deque = collections.deque(maxlen=64)   # (t_effective, qd), from any thread
        self.protective_stop: float | None = None   # the force (N) that stopped the arm, until `unlock`
        self._pending: collections.deque = collections.deque()        # owned by the physics thread
        self._qd_cmd = np.zeros(model.nq)
        self._t_cmd = self.t                 # when the command in force took effect
        self._lock = threading.Condition()   # guards commands, state and truth; notified on each new state
        self._state = JointState(t=clock(), q=self.q.copy(), qd=self.qd.copy(), seq=0, tcp_twist=twist.copy())
        self._new_states: collections.deque = collections.deque(maxlen=STATE_BACKLOG)
        self._truth = self._make_truth()
        self._next_proprio = self.t          # the proprioception schedule starts at the robot's clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.overruns = 0
        self.watchdog_stops = 0

    # -- RobotReceive -------------------------------------------------------
    def read_state(self) -> JointState:
        with self._lock:
            return self._state

    def truth(self) -> SimTruth | None:
        with self._lock:
            return self._truth

    def drain_states(self) -> list[JointState]:
        """Every proprioception sample published since the last drain (at most STATE_BACKLOG), oldest first."""
        with self._lock:
            out = list(self._new_states)
            self._new_states.clear()
        return out

    def wait_state(self, seq: int, timeout: float) -> JointState:
        """The latest state, once its seq differs from `seq` or after `timeout` s."""
        with self._lock:
            self._lock.wait_for(lambda: self._state.seq != seq, timeout)
            return self._state

    # -- RobotControl -------------------------------------------------------
    def command_joint_velocity(self, qd: np.ndarray) -> None:
        self.command_at(self.clock(), qd)

    def command_at(self, t_issued: float, qd: np.ndarray) -> None:
        """A command issued at `t_issued` (this clock): it takes effect command_latency_s later."""
        qd = joint_rates(qd, self.model.nq)
        with self._lock:
            self._cmds.append((t_issued + self.p.command_latency_s, qd.copy()))

    def hold(self) -> None:
        self.command_joint_velocity(np.zeros(self.model.nq))

    def unlock(self) -> float | None:
        """Release the simulated controller's protective stop (`recover`); the arm stays at rest until commanded.
        While the force at the TCP is still beyond the limit the stop holds (a real controller's recurs at once):
        that force is returned, else None."""
        force = float(np.linalg.norm(self.world.tcp_force())) if self.world is not None else 0.0
        if self.protective_stop is not None and force > self.p.protective_stop_force_n:
            log.info("sim: the protective stop holds: still %.1f N at the TCP", force)
            return force
        if self.protective_stop is not None:
            log.info("sim: the protective stop is unlocked")
        self.protective_stop = None
        return None

    # -- lifecycle ----------------------------------------------------------
    def sync_clock(self) -> None:
        """Start the physics (and the proprioception schedule) from the clock's now, for a caller
        that drives `advance_to` itself in real time."""
        self.t = self.clock()
        self._next_proprio = self.t

    def start(self) -> None:
        self.sync_clock()
        self._thread = threading.Thread(target=self._run, name="sim-physics", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def _run(self) -> None:
        t_next = time.monotonic()
        while not self._stop.is_set():
            t_next += PHYSICS_WAKE_S
            try:
                self.advance_to(self.clock())
            except Exception:
                log.exception("sim physics failed")
                raise
            delay = t_next - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                self.overruns += 1
                if delay < -0.1:
                    t_next = time.monotonic()

    # -- physics ------------------------------------------------------------
    def advance_to(self, t_end: float) -> None:
        """Integrate at 1 kHz up to t_end (s, monotonic) and feed the IMU."""
        dt = 1.0 / PHYSICS_RATE_HZ
        n = int((t_end - self.t) / dt)
        if n <= 0:
            return
        ts = np.empty(n + 1)
        w_tcp = np.empty((n + 1, 3))
        w_obj = np.empty((n + 1, 3))
        a_tcp = np.empty((n + 1, 3))
        v_tcp = np.empty((n + 1, 3))
        Rs = np.empty((n + 1, 3, 3))
        with self._lock:
            self._pending.extend(self._cmds)
            self._cmds.clear()
        pending = self._pending
        timeout = self.p.command_timeout_s
        alpha = 1.0 if self.p.tracking_tau_s <= 0 else 1.0 - math.exp(-dt / self.p.tracking_tau_s)
        model = self.model
        for k in range(n + 1):
            if k > 0:
                t = self.t + dt
                while pending and pending[0][0] <= t:
                    self._t_cmd, self._qd_cmd = pending.popleft()
                if self.protective_stop is not None:
                    self._qd_cmd = np.zeros(self.model.nq)      # held until `recover` unlocks it
                if timeout > 0 and t - self._t_cmd > timeout and self._qd_cmd.any():
                    self._qd_cmd = np.zeros(self.model.nq)      # the arm's own stop: the controller went quiet
                    self.watchdog_stops += 1
                    log.warning("sim: no joint command for %.0f ms, the arm stops", (t - self._t_cmd) * 1e3)
                # np.minimum/np.maximum in place: np.clip's Python wrapper costs ten times more on 7 joints
                qd = self.qd
                qd += alpha * (self._qd_cmd - qd)
                np.minimum(np.maximum(qd, model.qd_min, out=qd), model.qd_max, out=qd)
                q = self.q + qd * dt
                self.q = np.minimum(np.maximum(q, model.q_min, out=q), model.q_max, out=q)
                self.t = t
            oMtcp, twist = self.model.fk_twist(self.q, self.qd)
            ts[k] = self.t
            w_tcp[k] = twist[3:]
            a_tcp[k] = (twist[:3] - self._v_prev) / dt if k > 0 else 0.0
            v_tcp[k] = twist[:3]
            self._v_prev = twist[:3]
            Rs[k] = oMtcp.rotation
            if self.world is not None:
                if k > 0 and self.world.step(oMtcp.translation, dt, oMtcp.rotation) and self.imu is not None:
                    # the object is hit or starts to move: the fingertip rings
                    direction, amplitude = self.world.ring(oMtcp.translation, twist[:3])
                    self.imu.impact(self.t, direction, float(np.linalg.norm(twist[:3])), amplitude)
                w_obj[k] = self.world.object_rate_world()
            else:
                w_obj[k] = twist[3:]
            if self.t >= self._next_proprio:
                self._next_proprio += 1.0 / self.p.proprio_rate_hz
                noisy_q = self.q + self.rng.normal(0.0, self.p.encoder_noise_rad, self.q.shape)
                reported = twist.copy()
                reported[:3] += self.rng.normal(0.0, self.p.tcp_speed_noise, 3)
                force = self.world.tcp_force() if self.world is not None else np.zeros(3)
                if self.protective_stop is None and float(np.linalg.norm(force)) > self.p.protective_stop_force_n:
                    self.protective_stop = float(np.linalg.norm(force))
                    log.warning("sim: protective stop: %.1f N at the TCP (limit %g N)", self.protective_stop,
                                self.p.protective_stop_force_n)
                with self._lock:
                    self._state = JointState(t=self.t, q=noisy_q, qd=self.qd.copy(), seq=self._state.seq + 1,
                                             tcp_twist=reported, tcp_force=force,
                                             wrench_source="sim_contact")
                    self._new_states.append(self._state)
                    self._lock.notify_all()
        a_tcp[0] = a_tcp[1] if n >= 1 else 0.0
        with self._lock:
            self._truth = self._make_truth()
        if self.imu is not None:
            self.imu.feed(ts, w_tcp, w_obj, a_tcp, Rs, v_tcp)

    def let_go(self) -> None:
        """The gripper lets go of the object: no world until `rebuild` (`home --reset-world`)."""
        with self._lock:
            self.world = None
            self._truth = None

    def rebuild_world(self) -> None:
        """A fresh world around the gripper where it is now, as at the start (the arm at q_home)."""
        if self._world_factory is None:
            return
        with self._lock:
            oMtcp = self.model.fk(self.q)
            self.world = self._world_factory(oMtcp.translation.copy(), oMtcp.rotation.copy())
            self._truth = self._make_truth()

    def _make_truth(self) -> SimTruth | None:
        return SimTruth(**self.world.truth()) if self.world is not None else None
