"""Jerk-limited Cartesian TCP trajectory with Ruckig, re-planned from a new target every control tick."""
from __future__ import annotations

import numpy as np
import ruckig


class PlannerError(RuntimeError):
    """Ruckig returned something other than Working or Finished; the message names the result."""


_OK = (ruckig.Result.Working, ruckig.Result.Finished)
# Ruckig's own numerical failures on valid input (pantor/ruckig#160), raised by this build:
# step 1 is an axis's fastest profile, step 2 the synchronisation of the axes.
_RETRY = (ruckig.Result.ErrorSynchronizationCalculation, ruckig.Result.ErrorExecutionTimeCalculation)
_CALC_FAILURES = ("error in step 1", "error in step 2", "error in time synchronization")


MAX_ADVANCE_TICKS = 5     # a tick later than this many periods advances the plan by this much only


class CartesianPlanner:
    """Owns Ruckig's InputParameter/OutputParameter for the TCP position (3 DOF, world, m).

    Each tick: `step(target_p, target_v)` runs `update()` then `pass_to_input()`,
    so the next plan starts from where this one says the TCP is one period later.
    Ticks do not come exactly one period apart on a loaded machine: `advance(now)`
    at the start of a tick moves the plan to where its last trajectory is at `now`,
    so the plan keeps wall time and rates taken from it (per wall second) stay true.
    Never uses intermediate waypoints (that path is not real-time).
    """

    def __init__(self, tick_s: float, max_speed: float, max_accel: float, max_jerk: float):
        if min(tick_s, max_speed, max_accel, max_jerk) <= 0:
            raise ValueError("planner limits: tick_s, max_speed, max_accel and max_jerk must be > 0")
        self.tick_s = tick_s
        self.max_speed = max_speed
        self.max_accel = max_accel
        self.max_jerk = max_jerk
        self.otg = ruckig.Ruckig(3, tick_s)
        self.inp = ruckig.InputParameter(3)
        self.out = ruckig.OutputParameter(3)
        self._set_limits(max_speed)
        self.result = ruckig.Result.Finished
        self._t_now: float | None = None      # the time of the current tick (advance)
        self._t_plan: float | None = None     # when the trajectory in `out` started (None: none to follow)
        self.fallbacks = 0                    # cycles planned axis by axis after a Ruckig failure (_update)

    def release(self) -> None:
        """Drop the Ruckig objects now (the planner is not used again). Freed by their reference count,
        not left to a garbage collection that the daemon's frozen heap would never run."""
        self.otg = self.inp = self.out = None

    def _set_limits(self, speed: float) -> None:
        # Ruckig limits are per axis. Targets here always carry a velocity of norm
        # <= speed, so per-axis `speed` keeps their direction intact (dividing by
        # sqrt(3) would clip and turn a tangent off the arc). The Cartesian norm
        # can exceed `speed` only transiently; the control thread clamps the
        # commanded twist to the configured maximum as the safety bound.
        s = min(speed, self.max_speed)
        self.inp.max_velocity = [s] * 3
        self.inp.max_acceleration = [self.max_accel] * 3
        self.inp.max_jerk = [self.max_jerk] * 3

    def set_speed(self, speed: float) -> None:
        """Cap the TCP speed of what follows (m/s per axis, at most the configured maximum)."""
        self._set_limits(speed)

    def reset(self, p: np.ndarray, v: np.ndarray | None = None, a: np.ndarray | None = None,
              speed: float | None = None) -> None:
        """Restart from the measured TCP state; `speed` caps the velocity of what follows (m/s)."""
        self.inp.current_position = list(map(float, p))
        self.inp.current_velocity = [0.0] * 3 if v is None else list(map(float, v))
        self.inp.current_acceleration = [0.0] * 3 if a is None else list(map(float, a))
        self.inp.control_interface = ruckig.ControlInterface.Position
        self._set_limits(self.max_speed if speed is None else speed)
        self._t_plan = None

    def advance(self, now: float) -> None:
        """Start a tick at `now` (s, monotonic): the plan's state becomes its last trajectory's at
        the time since that trajectory began (one period on time; more after a late tick, less
        in the tick that catches up), at most MAX_ADVANCE_TICKS periods."""
        if self._t_plan is not None:
            elapsed = min(max(now - self._t_plan, 0.0), MAX_ADVANCE_TICKS * self.tick_s)
            if abs(elapsed - self.tick_s) > 1e-6:
                # out.time is where the last new state lies on the trajectory (Ruckig follows an
                # unchanged input's trajectory on without re-planning it)
                p, v, a = self.out.trajectory.at_time(self.out.time - self.tick_s + elapsed)
                self.inp.current_position, self.inp.current_velocity, self.inp.current_acceleration = p, v, a
        self._t_plan = None
        self._t_now = now

    @property
    def position(self) -> np.ndarray:
        return np.array(self.inp.current_position)

    @property
    def velocity(self) -> np.ndarray:
        return np.array(self.inp.current_velocity)

    def step(self, target_p: np.ndarray, target_v: np.ndarray | None = None,
             min_duration_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Plan towards (target_p, target_v), taking at least min_duration_s, and advance one tick;
        returns the new (p, v)."""
        self.inp.control_interface = ruckig.ControlInterface.Position
        self.inp.minimum_duration = min_duration_s if min_duration_s and min_duration_s > self.tick_s else None
        self.inp.target_position = list(map(float, target_p))
        tv = np.zeros(3) if target_v is None else np.asarray(target_v, dtype=float)
        # A target velocity beyond the per-axis limit is infeasible: scale it
        # uniformly into the box so that its direction is kept.
        lim = self.inp.max_velocity[0]
        peak = float(np.max(np.abs(tv)))
        if peak > lim:
            tv = tv * (lim * (1.0 - 1e-9) / peak)    # rounding must not leave it a hair over the limit
        self.inp.target_velocity = list(map(float, tv))
        self.inp.target_acceleration = [0.0] * 3
        return self._update()

    def brake(self) -> tuple[np.ndarray, np.ndarray]:
        """Decelerate to rest within the jerk and acceleration limits (velocity interface)."""
        self.inp.control_interface = ruckig.ControlInterface.Velocity
        self.inp.minimum_duration = None
        self.inp.target_velocity = [0.0] * 3
        self.inp.target_acceleration = [0.0] * 3
        return self._update()

    def _calculate(self) -> ruckig.Result:
        try:
            return self.otg.update(self.inp, self.out)
        except ruckig.RuckigError as exc:   # raised instead of returned for invalid input
            lines = str(exc).strip().splitlines()
            reason = next((ln for ln in lines if ln.startswith("[ruckig]")), lines[-1] if lines else "")
            reason = reason.removeprefix("[ruckig]").strip()
            if any(s in reason for s in _CALC_FAILURES):
                return ruckig.Result.ErrorExecutionTimeCalculation if "step 1" in reason \
                    else ruckig.Result.ErrorSynchronizationCalculation
            raise PlannerError(f"ruckig: ErrorInvalidInput: {reason}") from None

    def _update(self) -> tuple[np.ndarray, np.ndarray]:
        result = self._calculate()
        if result in _RETRY:
            # Ruckig fails numerically on rare valid inputs, at a knife edge of its root finding
            # (about 1 in 10^4 random re-plans here; pantor/ruckig#160). Plan this one cycle with
            # each axis on its own and no minimum duration, and if that fails too, from a state
            # a part in 10^9 slower: the next tick re-plans the full path from where this one ends.
            duration, self.inp.minimum_duration = self.inp.minimum_duration, None
            self.inp.synchronization = ruckig.Synchronization.No
            try:
                result = self._calculate()
                if result in _RETRY:
                    self.inp.current_velocity = [x * (1.0 - 1e-9) for x in self.inp.current_velocity]
                    self.inp.current_acceleration = [x * (1.0 - 1e-9) for x in self.inp.current_acceleration]
                    result = self._calculate()
            finally:
                self.inp.synchronization = ruckig.Synchronization.Time
                self.inp.minimum_duration = duration
            self.fallbacks += 1
        if result not in _OK:
            raise PlannerError(f"ruckig: {result.name}")
        self.result = result
        self.out.pass_to_input(self.inp)
        self._t_plan = self._t_now
        return np.array(self.out.new_position), np.array(self.out.new_velocity)

    def steady(self, speed: float, rel_tol: float = 0.05, accel_tol: float = 0.02) -> bool:
        """Moving at `speed` (m/s) with no acceleration: the planned motion has settled."""
        v = float(np.linalg.norm(self.inp.current_velocity))
        a = float(np.linalg.norm(self.inp.current_acceleration))
        return abs(v - speed) <= rel_tol * speed and a <= accel_tol

    @property
    def finished(self) -> bool:
        return self.result == ruckig.Result.Finished

    @property
    def at_rest(self) -> bool:
        return float(np.linalg.norm(self.inp.current_velocity)) < 1e-5 and \
            float(np.linalg.norm(self.inp.current_acceleration)) < 1e-4
