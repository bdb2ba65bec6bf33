"""`wrist`: turn the gripper in place about each of its own axes, for `tecdard calibrate-mount --live`."""
from __future__ import annotations

import math

from tecdard.control.wrist import WristTask
from tecdard.verbs import Field, TaskVerb

FIELDS = (
    Field("amplitude_deg", "number", 10.0, 1.0, lambda lim: min(10.0, lim.max_rotation_deg), "deg",
          "how far the wrist turns each way about each TCP axis (at most 10 deg, and limits.max_rotation_deg)"),
    Field("rate_deg_s", "number", 5.0, 1.0, 20.0, "deg/s", "how fast it turns"),
)


def build(f: dict, ctx) -> WristTask:
    return WristTask(ctx.task_id, math.radians(f["amplitude_deg"]), math.radians(f["rate_deg_s"]))


VERB = TaskVerb("wrist", "turn the gripper in place about each TCP axis (mount calibration)", FIELDS, build,
                example="tecdard wrist --amplitude-deg 10 --rate-deg-s 5")
