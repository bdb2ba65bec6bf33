"""`home`: a slow joint move to robot.q_home (every backend); with `reset_world` on the simulated robot,
the held object is let go first and a fresh world is built around the gripper once home."""
from __future__ import annotations

import math

from tecdard.control.home import HomeRefused, HomeTask, plan_home
from tecdard.verbs import BuildRefused, Field, TaskVerb

FIELDS = (
    Field("joint_speed_deg_s", "number", lambda lim: lim.default_home_joint_speed_deg_s, 1.0,
          lambda lim: lim.max_home_joint_speed_deg_s, "deg/s",
          "the fastest joint's speed (the TCP also stays under limits.max_speed)"),
    Field("reset_world", "bool", False,
          help="simulated robot only: let go of the object, home, and build a fresh world there"),
)


def build(f: dict, ctx) -> HomeTask:
    if ctx.q is None or ctx.q_home is None or ctx.fk is None:
        raise BuildRefused("home: this daemon gives the task no joint state")
    world = ctx.world
    if f["reset_world"] and world is None:
        raise BuildRefused("reset_world: only the simulated robot has a world to reset; on a real arm, open "
                           "the gripper and set the object back by hand")
    speed = math.radians(f["joint_speed_deg_s"])
    try:
        traj = plan_home(ctx.q, ctx.q_home, speed, ctx.max_speed_m_s, ctx.fk, ctx.workspace_min, ctx.workspace_max)
    except HomeRefused as exc:
        raise BuildRefused(str(exc)) from None
    return HomeTask(ctx.task_id, ctx.q, ctx.q_home, traj, speed,
                    on_start=world.let_go if f["reset_world"] else None,
                    on_home=world.rebuild if f["reset_world"] else None)


VERB = TaskVerb("home", "move the joints slowly to robot.q_home", FIELDS, build,
                example="tecdard home --joint-speed-deg-s 10")
