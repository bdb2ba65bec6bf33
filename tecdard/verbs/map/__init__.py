"""`map`: probe a grid of points below the TCP and write a tactile depth map."""
from __future__ import annotations

import math

import numpy as np

from tecdard.control.mapping import MapParams, MapTask
from tecdard.verbs import BuildRefused, Field, TaskVerb
from tecdard.verbs.map.files import MapFiles

MAP_AIM_MARGIN_M = 0.01      # a map's planned TCP positions keep this far inside the workspace box (x, y)

FIELDS = (
    Field("grid", "grid", [5, 6], help="rows,cols (rows along +y)"),
    Field("orientations", "int_choice", 2, choices=(1, 2), help="1, or 2 (a second pass, tool turned 90 deg)"),
    Field("origin", "numbers", None, -10.0, 10.0, "m", "x,y of the region's corner (m, world; default: centred "
                                                       "below the TCP)", n=2),
    Field("size", "numbers", lambda lim: lim.default_map_size, 0.005, lambda lim: lim.max_map_size, "m",
          "x,y extent (m)", n=2),
    Field("depth", "number", lambda lim: lim.default_map_depth, 0.005, lambda lim: lim.max_map_depth, "m",
          "deepest descent below the start height (m)"),
    Field("speed", "number", lambda lim: lim.default_map_speed, lambda lim: lim.min_speed,
          lambda lim: lim.max_speed, "m/s", "descent and probe speed (m/s)"),
)


def build(f: dict, ctx) -> MapTask:
    """A map run; refused when any of its moves would leave the workspace box."""
    ms = ctx.service.settings
    p = ctx.p_tcp
    size = np.array(f["size"])
    origin = np.array(f["origin"]) if f["origin"] is not None else p[:2] - size / 2
    # Ruckig caps each axis: a diagonal travel at max_speed / sqrt(2) stays within max_speed
    params = MapParams(origin_xy=origin, size_xy=size, grid=tuple(f["grid"]), depth=f["depth"],
                       orientations=f["orientations"], speed=f["speed"],
                       travel_speed=ctx.max_speed_m_s / math.sqrt(2.0),
                       probe_distance=ms.probe_distance_m, abort_force_n=ms.abort_force_n,
                       max_point_std_m=ms.max_point_std_m, tool_tip_tcp=np.array(ms.tool_tip_tcp),
                       turn_yaw_rad=math.radians(ms.turn_deg), release_distance=ms.release_distance_m)
    task = MapTask(ctx.task_id, params, ctx.service)
    margin = np.array([MAP_AIM_MARGIN_M, MAP_AIM_MARGIN_M, 0.0])
    lo, hi = np.array(ctx.workspace_min) + margin, np.array(ctx.workspace_max) - margin
    for name, z in (("origin", p[2]), ("depth", p[2] - f["depth"])):
        for xy in task.planned_tcp_xy(ctx.R_hold):
            q = np.array([xy[0], xy[1], z])
            # the tool model aims the TCP; what each probe measures refines it by millimetres
            if np.any(q < lo) or np.any(q > hi):
                raise BuildRefused(f"{name}: the map takes the TCP to {np.round(q, 3).tolist()}, "
                                   "outside the workspace box")
    return task


VERB = TaskVerb("map", "probe a grid and write a tactile depth map", FIELDS, build, service=MapFiles.from_config,
               example="tecdard map --origin 0.31,-0.165 --size 0.43,0.33 --grid 5,6 --depth 0.25")
