"""`probe`: a straight probe along `direction` that localises the contact it makes."""
from __future__ import annotations

import numpy as np

from tecdard.control.rotate import ProbeTask
from tecdard.verbs import Field, TaskVerb

FIELDS = (
    Field("direction", "direction", lambda lim: lim.default_direction, help="unit vector x,y,z (world)"),
    Field("distance", "number", lambda lim: lim.default_probe_distance, 0.0005, lambda lim: lim.max_probe_distance,
          "m", "probe length"),
    Field("speed", "number", lambda lim: lim.default_speed, lambda lim: lim.min_speed, lambda lim: lim.max_speed,
          "m/s", "TCP speed"),
)


def build(f: dict, ctx) -> ProbeTask:
    return ProbeTask(ctx.task_id, f["speed"], f["distance"], np.array(f["direction"]))


VERB = TaskVerb("probe", "probe along a direction and localise the contact", FIELDS, build,
                example="tecdard probe --direction 0,0,-1 --distance 0.005 --speed 0.005")
