"""Validation of `tecdar/1` command payloads: bytes in, normalised fields or a coded one-line error out.

Every payload is untrusted: its size is checked before it is decoded, it is parsed with bounded
nesting and number lengths (tecdard.safejson), every number is converted with range and
finiteness checks, and anything a sender wrote is echoed back escaped and truncated.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from tecdard.safejson import JsonLimitError, finite, is_number, loads, show, show_name

log = logging.getLogger("tecdar.commands")

VERBS = ("probe", "rotate", "point", "approach", "map", "stop", "status", "cancel")
TASK_VERBS = ("probe", "rotate", "point", "approach", "map")

# Error codes of the reply {"ok": false, "error": {"code", "message"}}.
BAD_JSON = "bad_json"
UNKNOWN_VERB = "unknown_verb"
UNKNOWN_FIELD = "unknown_field"
MISSING_FIELD = "missing_field"
BAD_TYPE = "bad_type"
OUT_OF_LIMITS = "out_of_limits"
BUSY = "busy"
NOT_IMPLEMENTED = "not_implemented"
NO_TASK = "no_task"
FAULT = "fault"
INTERNAL = "internal"
BAD_REQUEST = "bad_request"              # the request could not be handled (a bug of ours: logged)
PAYLOAD_TOO_LARGE = "payload_too_large"
RATE_LIMITED = "rate_limited"

UNIT_TOL = 1e-3   # a direction must have |d| within this of 1
MAX_PAYLOAD_BYTES = 16384     # a command payload is refused unread beyond this (the largest real one is ~200 B)
MAX_TASK_ID_CHARS = 64
MAP_SPEED_M_S = 0.01          # a map's default descent and probe speed (the paper's 1 cm/s), within the limits


class CommandError(Exception):
    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message

    def reply(self) -> dict:
        return {"ok": False, "error": {"code": self.code, "message": self.message}}


@dataclass
class Limits:
    """Configured bounds that commands are checked against (SI)."""
    max_speed: float = 0.05            # m/s
    min_speed: float = 0.001           # m/s
    max_rotation_deg: float = 90.0
    max_probe_distance: float = 0.02   # m
    default_speed: float = 0.02        # m/s
    default_probe_distance: float = 0.005
    default_direction: tuple = (0.0, 0.0, 1.0)
    max_approach_distance: float = 0.2     # m
    default_stop_angle_deg: float = 5.0
    default_point_radius: float = 0.01     # m, circular probing
    max_point_radius: float = 0.03         # m
    max_point_turns: float = 5.0
    default_map_size: tuple = (0.1, 0.1)   # m, x and y extent of a map region
    max_map_size: float = 1.0              # m, per side
    default_map_depth: float = 0.1         # m, deepest descent below the start height
    max_map_depth: float = 0.4             # m
    max_map_points: int = 400              # rows x cols

    @property
    def default_map_speed(self) -> float:
        """A map descends and probes at up to 10 mm/s (the paper's), within the speed limits."""
        return min(max(MAP_SPEED_M_S, self.min_speed), self.default_speed)

    @classmethod
    def from_config(cls, section) -> "Limits":
        """Every option of `limits`, each bounded, and every default checked against its limit: a
        default beyond its maximum would move the robot further than the config allows."""
        from tecdard.config import ConfigError
        limits = cls._read(section)
        for verb, required in SELF_CHECK.items():
            try:
                validate(verb, dict(required), limits)
            except CommandError as exc:
                field = exc.message.split(":")[0]
                key = DEFAULT_KEYS.get(field, f"default_{field}")
                raise ConfigError(f"{section.path}.{key}: the default is outside its own limits "
                                  f"('{verb}' {exc.message})") from None
        return limits

    @classmethod
    def _read(cls, section) -> "Limits":
        d = cls()
        max_speed = section.getfloat("max_speed", d.max_speed, above=0.0, maxval=0.5)
        return cls(
            max_speed=max_speed,
            min_speed=section.getfloat("min_speed", d.min_speed, above=0.0, maxval=max_speed),
            max_rotation_deg=section.getfloat("max_rotation_deg", d.max_rotation_deg, above=0.0, maxval=180.0),
            max_probe_distance=section.getfloat("max_probe_distance", d.max_probe_distance, above=0.0, maxval=0.1),
            default_speed=section.getfloat("default_speed", d.default_speed, above=0.0, maxval=max_speed),
            default_probe_distance=section.getfloat("default_probe_distance", d.default_probe_distance, above=0.0),
            default_direction=tuple(section.getvec3("default_direction", list(d.default_direction), unit=True)),
            max_approach_distance=section.getfloat("max_approach_distance", d.max_approach_distance, above=0.0,
                                                   maxval=1.0),
            default_stop_angle_deg=section.getfloat("default_stop_angle_deg", d.default_stop_angle_deg, above=0.0,
                                                    maxval=90.0),
            default_point_radius=section.getfloat("default_point_radius", d.default_point_radius, above=0.0,
                                                  maxval=0.1),
            max_point_radius=section.getfloat("max_point_radius", d.max_point_radius, above=0.0, maxval=0.1),
            max_point_turns=section.getfloat("max_point_turns", d.max_point_turns, minval=0.25, maxval=20.0),
            default_map_size=tuple(section.getfloats("default_map_size", list(d.default_map_size), n=2,
                                                     minval=0.005, maxval=2.0)),
            max_map_size=section.getfloat("max_map_size", d.max_map_size, above=0.0, maxval=2.0),
            default_map_depth=section.getfloat("default_map_depth", d.default_map_depth, above=0.0, maxval=1.0),
            max_map_depth=section.getfloat("max_map_depth", d.max_map_depth, above=0.0, maxval=1.0),
            max_map_points=section.getint("max_map_points", d.max_map_points, minval=1, maxval=10000),
        )


# A command of each verb with only its required fields: every default is used, so Limits.from_config
# can check that each one passes its own limits.
SELF_CHECK = {"probe": {}, "rotate": {"angle_deg": 0.1}, "point": {}, "approach": {"direction": [0.0, 0.0, -1.0]},
              "map": {}, "stop": {}, "status": {}, "cancel": {}}


# The limits key that holds each field's default.
DEFAULT_KEYS = {"distance": "default_probe_distance", "probe_distance": "default_probe_distance",
                "radius": "default_point_radius", "depth": "default_map_depth", "size": "default_map_size",
                "speed": "default_speed", "stop_angle_deg": "default_stop_angle_deg",
                "max_distance": "max_approach_distance", "direction": "default_direction"}


def parse_payload(raw: str | bytes | None) -> dict:
    """The command's JSON object ({} for an empty payload); CommandError for anything else: a
    payload over MAX_PAYLOAD_BYTES (checked before decoding), bytes that are not UTF-8, malformed
    or too deeply nested JSON, over-long or non-finite numbers, or a JSON value that is no object."""
    if raw is None:
        return {}
    if len(raw) > MAX_PAYLOAD_BYTES:
        raise CommandError(PAYLOAD_TOO_LARGE, f"payload: {len(raw)} bytes, at most {MAX_PAYLOAD_BYTES}")
    if isinstance(raw, (bytes, bytearray, memoryview)):
        try:
            raw = bytes(raw).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CommandError(BAD_JSON, f"payload: not valid UTF-8 (byte {exc.start})") from None
    if raw.strip() == "":
        return {}
    try:
        obj = loads(raw)
    except JsonLimitError as exc:
        raise CommandError(BAD_JSON, f"payload: {exc}") from None
    if not isinstance(obj, dict):
        raise CommandError(BAD_JSON, f"payload: expected a JSON object, got {type(obj).__name__}")
    return obj


def admit(verb: str, raw: str | bytes | None, limits: "Limits") -> dict:
    """parse_payload then validate, as one boundary: CommandError for a bad command, and for any
    other exception (a bug in validation) CommandError BAD_REQUEST with the traceback logged."""
    try:
        return validate(verb, parse_payload(raw), limits)
    except CommandError:
        raise
    except Exception as exc:
        log.exception("validating a '%s' command failed", show_name(verb))
        raise CommandError(BAD_REQUEST, f"{show_name(verb)}: the request could not be handled "
                                        f"({type(exc).__name__}, logged)") from None


def _number(obj: dict, name: str, default, lo: float, hi: float, unit: str) -> float:
    if name not in obj:
        if default is None:
            raise CommandError(MISSING_FIELD, f"{name}: required field is missing")
        if not lo <= default <= hi:       # Limits.from_config refuses such a config; never act on one
            raise CommandError(OUT_OF_LIMITS, f"{name}: the configured default {default:g} {unit} is outside "
                                              f"the configured limits [{lo:g}, {hi:g}]")
        return float(default)
    v = finite(obj[name])
    if v is None:
        raise CommandError(BAD_TYPE, f"{name}: expected a finite number, got {show(obj[name])}")
    if v < lo or v > hi:
        raise CommandError(OUT_OF_LIMITS, f"{name}: {v:g} {unit} is outside the configured limits [{lo:g}, {hi:g}]")
    return v


def _direction(obj: dict, name: str, default) -> list[float]:
    if name not in obj:
        if default is None:
            raise CommandError(MISSING_FIELD, f"{name}: required field is missing")
        return list(default)
    v = obj[name]
    xs = [finite(x) for x in v] if isinstance(v, list) and len(v) == 3 else None
    if xs is None or any(x is None for x in xs):
        raise CommandError(BAD_TYPE, f"{name}: expected a unit vector [x, y, z], got {show(v)}")
    norm = math.hypot(*xs)          # no overflow for components near the float64 range
    if not abs(norm - 1.0) <= UNIT_TOL:
        raise CommandError(OUT_OF_LIMITS, f"{name}: expected a unit vector, |{name}| = {norm:.4g}")
    return [x / norm for x in xs]


def _numbers(obj: dict, name: str, default, n: int, lo: float, hi: float, unit: str) -> list[float] | None:
    """A list of n finite numbers within [lo, hi] (default when absent; None default: may be absent)."""
    if name not in obj:
        if default is not None and not all(lo <= x <= hi for x in default):
            raise CommandError(OUT_OF_LIMITS, f"{name}: the configured default {list(default)} {unit} is outside "
                                              f"the configured limits [{lo:g}, {hi:g}]")
        return None if default is None else [float(x) for x in default]
    v = obj[name]
    xs = [finite(x) for x in v] if isinstance(v, list) and len(v) == n else None
    if xs is None or any(x is None for x in xs):
        raise CommandError(BAD_TYPE, f"{name}: expected {n} finite numbers, got {show(v)}")
    for x in xs:
        if x < lo or x > hi:
            raise CommandError(OUT_OF_LIMITS, f"{name}: {x:g} {unit} is outside the configured limits [{lo:g}, {hi:g}]")
    return xs


def _check_fields(obj: dict, verb: str, allowed: tuple) -> None:
    for key in obj:
        if key not in allowed:
            raise CommandError(UNKNOWN_FIELD, f"{show_name(key)}: not a field of '{verb}' "
                                              f"(fields: {', '.join(allowed) or 'none'})")


def validate(verb: str, obj: dict, limits: Limits) -> dict:
    """Normalised command fields with defaults applied; CommandError on anything wrong."""
    if verb not in VERBS:
        raise CommandError(UNKNOWN_VERB, f"verb: unknown command '{show_name(verb)}' (known: {', '.join(VERBS)})")
    if verb == "rotate":
        _check_fields(obj, verb, ("angle_deg", "speed", "probe_distance", "direction", "strategy", "turn_tool"))
        strategy = obj.get("strategy", "arc")
        if not isinstance(strategy, str) or strategy not in ("arc", "straight"):
            raise CommandError(BAD_TYPE, f"strategy: expected \"arc\" or \"straight\", got {show(strategy)}")
        turn_tool = obj.get("turn_tool", True)
        if not isinstance(turn_tool, bool):
            raise CommandError(BAD_TYPE, f"turn_tool: expected true or false, got {show(turn_tool)}")
        return {
            "angle_deg": _number(obj, "angle_deg", None, 0.1, limits.max_rotation_deg, "deg"),
            "speed": _number(obj, "speed", limits.default_speed, limits.min_speed, limits.max_speed, "m/s"),
            "probe_distance": _number(obj, "probe_distance", limits.default_probe_distance, 0.0005,
                                      limits.max_probe_distance, "m"),
            "direction": _direction(obj, "direction", limits.default_direction),
            "strategy": strategy,
            "turn_tool": turn_tool,
        }
    if verb == "probe":
        _check_fields(obj, verb, ("direction", "distance", "speed"))
        return {
            "direction": _direction(obj, "direction", limits.default_direction),
            "distance": _number(obj, "distance", limits.default_probe_distance, 0.0005,
                                limits.max_probe_distance, "m"),
            "speed": _number(obj, "speed", limits.default_speed, limits.min_speed, limits.max_speed, "m/s"),
        }
    if verb == "approach":
        _check_fields(obj, verb, ("direction", "speed", "max_distance", "stop_angle_deg"))
        return {
            "direction": _direction(obj, "direction", None),
            "speed": _number(obj, "speed", limits.default_speed, limits.min_speed, limits.max_speed, "m/s"),
            "max_distance": _number(obj, "max_distance", limits.max_approach_distance, 0.001,
                                    limits.max_approach_distance, "m"),
            "stop_angle_deg": _number(obj, "stop_angle_deg", limits.default_stop_angle_deg, 0.1,
                                      limits.max_rotation_deg, "deg"),
        }
    if verb == "point":
        _check_fields(obj, verb, ("radius", "speed", "turns"))
        return {
            "radius": _number(obj, "radius", limits.default_point_radius, 0.002, limits.max_point_radius, "m"),
            "speed": _number(obj, "speed", limits.default_speed, limits.min_speed, limits.max_speed, "m/s"),
            "turns": _number(obj, "turns", 1.0, 0.25, limits.max_point_turns, "turns"),
        }
    if verb == "map":
        _check_fields(obj, verb, ("origin", "size", "grid", "depth", "orientations", "speed"))
        grid = obj.get("grid", [5, 6])
        if (not isinstance(grid, list) or len(grid) != 2
                or not all(isinstance(x, int) and not isinstance(x, bool) for x in grid)):
            raise CommandError(BAD_TYPE, f"grid: expected [rows, cols] as two integers, got {show(grid)}")
        if min(grid) < 1 or grid[0] * grid[1] > limits.max_map_points:
            raise CommandError(OUT_OF_LIMITS, f"grid: {grid[0]} x {grid[1]} points is outside the configured limits "
                                              f"(at least 1 x 1, at most {limits.max_map_points} points)")
        orientations = obj.get("orientations", 2)
        if not is_number(orientations) or orientations not in (1, 2):
            raise CommandError(BAD_TYPE, f"orientations: expected 1 or 2, got {show(orientations)}")
        return {
            "origin": _numbers(obj, "origin", None, 2, -10.0, 10.0, "m"),
            "size": _numbers(obj, "size", limits.default_map_size, 2, 0.005, limits.max_map_size, "m"),
            "grid": [int(grid[0]), int(grid[1])],
            "depth": _number(obj, "depth", limits.default_map_depth, 0.005, limits.max_map_depth, "m"),
            "orientations": int(orientations),
            "speed": _number(obj, "speed", limits.default_map_speed, limits.min_speed, limits.max_speed, "m/s"),
        }
    if verb in ("stop", "status"):
        _check_fields(obj, verb, ())
        return {}
    if verb == "cancel":
        _check_fields(obj, verb, ("task",))
        task = obj.get("task")
        if task is not None and (not isinstance(task, str) or len(task) > MAX_TASK_ID_CHARS):
            raise CommandError(BAD_TYPE, f"task: expected a task id string (at most {MAX_TASK_ID_CHARS} "
                                         f"characters), got {show(task)}")
        return {"task": task}
    raise CommandError(NOT_IMPLEMENTED, f"verb: '{verb}' is not implemented yet")
