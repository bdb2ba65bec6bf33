"""The node's parameters, read-only: the daemon's effective config as rcl_interfaces parameters.

`ros2 param list`, `get`, `describe` and `get_parameter_types` on the node timed out before: rclcpp
serves these services on every node, and ROS 2's tools expect them. Here every option the daemon
reads (tecdard options) is one parameter, named as its config key (`control.max_force_n`). Its value
is the config's, or the option's default where the config leaves it out. Its descriptor is read-only
and carries the option's help, its unit and its declared limits as a range. `set_parameters` and
`set_parameters_atomically` answer `successful: false` with the reason "restart with a changed
config". The set is published once on `/parameter_events` at start.
"""
from __future__ import annotations

import json
import math

# The six services of rcl_interfaces (Kilted; the same in Jazzy and Humble), as their .srv files say them (the
# message types named with their package, which rosbags resolves; the same types rosidl hashes)
SRV_TEXTS = {
    "rcl_interfaces/srv/ListParameters": "uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth\n---\n"
                                         "rcl_interfaces/ListParametersResult result\n",
    "rcl_interfaces/srv/GetParameters": "string[] names\n---\nrcl_interfaces/ParameterValue[] values\n",
    "rcl_interfaces/srv/GetParameterTypes": "string[] names\n---\nuint8[] types\n",
    "rcl_interfaces/srv/DescribeParameters": "string[] names\n---\nrcl_interfaces/ParameterDescriptor[] descriptors\n",
    "rcl_interfaces/srv/SetParameters": "rcl_interfaces/Parameter[] parameters\n---\nrcl_interfaces/SetParametersResult[] results\n",
    "rcl_interfaces/srv/SetParametersAtomically": "rcl_interfaces/Parameter[] parameters\n---\nrcl_interfaces/SetParametersResult result\n",
}
SERVICES = {"list_parameters": "rcl_interfaces/srv/ListParameters",
            "get_parameters": "rcl_interfaces/srv/GetParameters",
            "get_parameter_types": "rcl_interfaces/srv/GetParameterTypes",
            "describe_parameters": "rcl_interfaces/srv/DescribeParameters",
            "set_parameters": "rcl_interfaces/srv/SetParameters",
            "set_parameters_atomically": "rcl_interfaces/srv/SetParametersAtomically"}
PARAMETER_EVENT = "rcl_interfaces/msg/ParameterEvent"
# rcl_interfaces/msg/ParameterType
NOT_SET, BOOL, INTEGER, DOUBLE, STRING, INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY = 0, 1, 2, 3, 4, 7, 8, 9
MAX_NAMES = 4096                  # names a request may ask for; more: answered for none (a flood's worth)
READ_ONLY_REASON = "the daemon's parameters are its config, read at start: restart with a changed config"
# the sections read whatever the config holds; the others (an arm's link, the simulator) only where it has them
ALWAYS = ("robot", "gripper", "zenoh", "ros2", "limits", "control", "map", "record", "store", "viz.foxglove", "imu",
          "estimator")


def _value_at(data, dotted: str):
    node = data
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None, False
        node = node[part]
    return node, True


def _typed(value) -> tuple[int, object]:
    """(ParameterType, the value as that type's field holds it)."""
    if value is None:
        return NOT_SET, None
    if isinstance(value, bool):
        return BOOL, value
    if isinstance(value, int):
        return INTEGER, value
    if isinstance(value, float):
        return DOUBLE, value
    if isinstance(value, str):
        return STRING, value
    if isinstance(value, (list, tuple)):
        if all(isinstance(x, str) for x in value):
            return STRING_ARRAY, list(value)
        if value and all(isinstance(x, int) and not isinstance(x, bool) for x in value):
            return INTEGER_ARRAY, list(value)
        if all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
            return DOUBLE_ARRAY, [float(x) for x in value]
    return STRING, json.dumps(value, default=str)          # a table ([[30, 2]]), a mapping: as its JSON


class ParameterSet:
    """name -> (ParameterType, value, description, (from, to) or None) of every option the config's daemon reads."""

    def __init__(self, config_data: dict, sections: list):
        """`sections`: (path, options class) of every section the daemon reads (tecdard.option_sections)."""
        from tecdard.options import declared, default_of
        self.params: dict[str, tuple[int, object, str, tuple | None]] = {}
        data = config_data if isinstance(config_data, dict) else {}
        for path, cls in sections:
            if path not in ALWAYS and not path.startswith("estimator.") and not _value_at(data, path)[1]:
                continue
            for f, opt in declared(cls):
                name = f"{path}.{opt.key or f.name}"
                value, given = _value_at(data, name)
                if not given:
                    if opt.required:
                        continue
                    value = default_of(f)
                kind, typed = _typed(_plain(value))
                unit = f" ({opt.unit})" if opt.unit else ""
                lo = opt.minval if opt.minval is not None else opt.above
                bounds = None if lo is None and opt.maxval is None else (lo, opt.maxval)
                self.params[name] = (kind, typed, opt.help + unit, bounds)

    def names(self, prefixes=(), depth: int = 0) -> list[str]:
        """The names under any of `prefixes` (all with none), at most `depth` levels below them (0: any)."""
        out = []
        for name in self.params:
            if prefixes and not any(name == p or name.startswith(p.rstrip(".") + ".") for p in prefixes):
                continue
            if depth and prefixes:
                base = next(p for p in prefixes if name == p or name.startswith(p.rstrip(".") + "."))
                if name[len(base):].lstrip(".").count(".") >= depth:
                    continue
            elif depth and name.count(".") >= depth:
                continue
            out.append(name)
        return out


def _plain(value):
    """A value as the config's YAML would say it: numpy arrays and tuples as lists."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, tuple):
        return [_plain(x) for x in value]
    if isinstance(value, list):
        return [_plain(x) for x in value]
    return value


def parameter_value(T, kind: int, value):
    """An rcl_interfaces/msg/ParameterValue."""
    import numpy as np
    return T["rcl_interfaces/msg/ParameterValue"](
        type=kind, bool_value=bool(value) if kind == BOOL else False,
        integer_value=int(value) if kind == INTEGER else 0, double_value=float(value) if kind == DOUBLE else 0.0,
        string_value=str(value) if kind == STRING else "", byte_array_value=np.zeros(0, np.uint8),
        bool_array_value=np.zeros(0, bool),
        integer_array_value=np.array(value if kind == INTEGER_ARRAY else [], np.int64),
        double_array_value=np.array(value if kind == DOUBLE_ARRAY else [], np.float64),
        string_array_value=list(value) if kind == STRING_ARRAY else [])


def descriptor(T, name: str, entry) -> object:
    """An rcl_interfaces/msg/ParameterDescriptor: read-only, its help and unit, its limits as a range."""
    kind, _value, text, bounds = entry
    float_range, int_range = [], []
    if bounds is not None and kind in (DOUBLE, DOUBLE_ARRAY):
        lo, hi = bounds
        float_range = [T["rcl_interfaces/msg/FloatingPointRange"](
            from_value=float(lo) if lo is not None else -math.inf, to_value=float(hi) if hi is not None else math.inf,
            step=0.0)]
    elif bounds is not None and kind in (INTEGER, INTEGER_ARRAY):
        lo, hi = bounds
        int_range = [T["rcl_interfaces/msg/IntegerRange"](
            from_value=int(lo) if lo is not None else -(1 << 63), to_value=int(hi) if hi is not None else (1 << 63) - 1,
            step=0)]
    return T["rcl_interfaces/msg/ParameterDescriptor"](
        name=name, type=kind, description=text[:1000], additional_constraints="", read_only=True,
        dynamic_typing=False, floating_point_range=float_range, integer_range=int_range)


def respond(ts, params: ParameterSet, srv_type: str, req):
    """The response message of `srv_type` to the decoded request `req`."""
    T = ts.store.types
    Resp = T[srv_type + "_Response"]
    if srv_type.endswith("/ListParameters"):
        names = params.names(list(req.prefixes), int(req.depth))
        prefixes = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
        return Resp(result=T["rcl_interfaces/msg/ListParametersResult"](names=names, prefixes=prefixes))
    if srv_type.endswith("/SetParameters") or srv_type.endswith("/SetParametersAtomically"):
        result = T["rcl_interfaces/msg/SetParametersResult"]
        if srv_type.endswith("/SetParameters"):
            return Resp(results=[result(successful=False, reason=READ_ONLY_REASON) for _ in req.parameters])
        return Resp(result=result(successful=False, reason=READ_ONLY_REASON))
    names = list(req.names)
    if len(names) > MAX_NAMES:
        names = []
    if srv_type.endswith("/GetParameters"):
        return Resp(values=[parameter_value(T, *params.params[n][:2]) if n in params.params
                            else parameter_value(T, NOT_SET, None) for n in names])
    if srv_type.endswith("/GetParameterTypes"):
        import numpy as np
        return Resp(types=np.array([params.params[n][0] if n in params.params else NOT_SET for n in names], np.uint8))
    return Resp(descriptors=[descriptor(T, n, params.params[n]) if n in params.params
                             else T["rcl_interfaces/msg/ParameterDescriptor"](
                                 name=n, type=NOT_SET, description="", additional_constraints="", read_only=True,
                                 dynamic_typing=False, floating_point_range=[], integer_range=[]) for n in names])


def parameter_event(ts, params: ParameterSet, node_fqn: str, stamp_s: float):
    """The set as one rcl_interfaces/msg/ParameterEvent (every parameter new), for /parameter_events at start."""
    T = ts.store.types
    sec = int(stamp_s)
    return T[PARAMETER_EVENT](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int((stamp_s - sec) * 1e9)), node=node_fqn,
        new_parameters=[T["rcl_interfaces/msg/Parameter"](name=n, value=parameter_value(T, kind, value))
                        for n, (kind, value, _t, _b) in params.params.items()],
        changed_parameters=[], deleted_parameters=[])
