"""`point`: circular probing about a point contact (a pen on its tip)."""
from __future__ import annotations

from tecdard.control.tasks import PointTask
from tecdard.verbs import Field, TaskVerb

FIELDS = (
    Field("radius", "number", lambda lim: lim.default_point_radius, 0.002, lambda lim: lim.max_point_radius, "m",
          "circle radius"),
    Field("speed", "number", lambda lim: lim.default_speed, lambda lim: lim.min_speed, lambda lim: lim.max_speed,
          "m/s", "TCP speed"),
    Field("turns", "number", 1.0, 0.25, lambda lim: lim.max_point_turns, "turns", "circles to run"),
)


def build(f: dict, ctx) -> PointTask:
    return PointTask(ctx.task_id, f["radius"], f["speed"], f["turns"])


VERB = TaskVerb("point", "circle about a point contact and localise it", FIELDS, build,
                example="tecdard point --radius 0.01 --turns 1")
