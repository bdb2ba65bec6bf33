"""`rotate`: probe, then turn the held object about the estimated hinge by `angle_deg` (the paper's Algorithm 2)."""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.rotate import RotateTask
from tecdard.verbs import Field, TaskVerb

FIELDS = (
    Field("angle_deg", "number", lo=0.1, hi=lambda lim: lim.max_rotation_deg, unit="deg",
          help="how far to turn the object"),
    Field("speed", "number", lambda lim: lim.default_speed, lambda lim: lim.min_speed, lambda lim: lim.max_speed,
          "m/s", "TCP speed"),
    Field("probe_distance", "number", lambda lim: lim.default_probe_distance, 0.0005,
          lambda lim: lim.max_probe_distance, "m", "phase-1 probe length"),
    Field("direction", "direction", lambda lim: lim.default_direction,
          help="the phase-1 probe, unit vector x,y,z (world): along the handle's tangent at the grasp. Not given "
               "after a rotate that left the TCP on its hinge's circle: the tangent there, onwards (the reply says "
               "so); else the configured default"),
    Field("strategy", "choice", "arc", choices=("arc", "straight"),
          help="arc: follow the estimated hinge; straight: the paper's pull, which drags an unfixed base"),
    Field("turn_tool", "bool", True, help="the gripper turns with the object (default; --no-turn-tool: held)"),
)


def build(f: dict, ctx) -> RotateTask:
    return RotateTask(ctx.task_id, math.radians(f["angle_deg"]), f["speed"], f["probe_distance"],
                      np.array(f["direction"]), f["strategy"], turn_tool=f["turn_tool"])


VERB = TaskVerb("rotate", "turn the held object about its estimated hinge", FIELDS, build,
                self_check={"angle_deg": 0.1},
                example="tecdard rotate --angle-deg 30 --speed 0.01")
