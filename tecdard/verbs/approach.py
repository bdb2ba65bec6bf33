"""`approach`: move along `direction` until a contact is detected, and localise it."""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.tasks import ApproachTask
from tecdard.verbs import Field, TaskVerb

FIELDS = (
    Field("direction", "direction", help="unit vector x,y,z (world)"),
    Field("speed", "number", lambda lim: lim.default_speed, lambda lim: lim.min_speed, lambda lim: lim.max_speed,
          "m/s", "TCP speed"),
    Field("max_distance", "number", lambda lim: lim.max_approach_distance, 0.001,
          lambda lim: lim.max_approach_distance, "m", "give up after this far"),
    Field("stop_angle_deg", "number", lambda lim: lim.default_stop_angle_deg, 0.1,
          lambda lim: lim.max_rotation_deg, "deg", "stop once the object has turned this much"),
)


def build(f: dict, ctx) -> ApproachTask:
    return ApproachTask(ctx.task_id, np.array(f["direction"]), f["speed"], f["max_distance"],
                        math.radians(f["stop_angle_deg"]))


VERB = TaskVerb("approach", "approach until contact and localise it", FIELDS, build,
                self_check={"direction": [0.0, 0.0, -1.0]},
                example="tecdard approach --direction 0,0,-1 --speed 0.01 --max-distance 0.05")
