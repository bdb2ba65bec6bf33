"""Validation of `tecdar/1` command payloads: bytes in, normalised fields or a coded one-line error out.

Every payload is untrusted: its size is checked before it is decoded, it is parsed with bounded
nesting and number lengths (tecdard.safejson), every number is converted with range and
finiteness checks, and anything a sender wrote is echoed back escaped and truncated.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from tecdard import verbs as task_verbs_registry
from tecdard.options import option, read_options
from tecdard.safejson import JsonLimitError, finite, is_number, loads, show, show_name
from tecdard.verbs import REQUIRED, Field, TaskVerb

log = logging.getLogger("tecdar.commands")

CONTROL_VERBS = ("stop", "status", "cancel", "record", "grasp", "release", "recover")   # the verbs that are not tasks
GRIP_VERBS = ("grasp", "release")         # the gripper's (robots/gripper.py), one at a time, never during a task


def task_verbs() -> tuple[str, ...]:
    """The task verbs: one module each in tecdard/verbs/."""
    return task_verbs_registry.names()


def verbs() -> tuple[str, ...]:
    return task_verbs() + CONTROL_VERBS

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
NOT_RECORDING = "not_recording"
READ_ONLY = "read_only"                  # the daemon observes an arm that something else drives
NO_GRIPPER = "no_gripper"                # gripper.backend: none (or an arm without one)
GRIPPER = "gripper"                      # the gripper refused, failed or did not answer
NOT_GRASPED = "not_grasped"              # a task, while a gripper that says what it holds holds nothing
NOT_RECOVERED = "not_recovered"          # `recover` could not return the arm to a state where tasks run: a person must
MAX_GRIP_FORCE_N = 300.0                 # the fields' own bounds; gripper.max_force_n bounds the force further
MAX_GRIP_WIDTH_M = 0.15
MAX_GRIP_SPEED_M_S = 0.2
RECORD_ACTIONS = ("start", "stop")
MAX_LABEL_CHARS = 64

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
    max_speed: float = option(0.05, "the TCP's speed limit of every task", unit="m/s", above=0.0, maxval=0.5)
    min_speed: float = option(0.001, "the slowest speed a task may ask (at most max_speed)", unit="m/s", above=0.0,
                              maxval=0.5)
    max_rotation_deg: float = option(90.0, "the largest rotation a task may ask", unit="deg", above=0.0,
                                     maxval=180.0)
    max_probe_distance: float = option(0.02, "the longest probe a task may ask", unit="m", above=0.0, maxval=0.1)
    default_speed: float = option(0.02, "a task's speed when it gives none (at most max_speed)", unit="m/s",
                                  above=0.0, maxval=0.5)
    default_probe_distance: float = option(0.005, "a task's probe when it gives none (the paper's 5 mm of "
                                                  "tangential probing)", unit="m", above=0.0)
    default_direction: tuple = option((0.0, 0.0, 1.0), "a task's probe direction when it gives none, world",
                                      kind="unitvec3")
    max_approach_distance: float = option(0.2, "an approach never travels further", unit="m", above=0.0, maxval=1.0)
    default_stop_angle_deg: float = option(5.0, "an approach finishes once the object has turned this much",
                                           unit="deg", above=0.0, maxval=90.0)
    default_point_radius: float = option(0.01, "point: the TCP's circle radius (the tool's tilt is radius / "
                                               "length)", unit="m", above=0.0, maxval=0.1)
    max_point_radius: float = option(0.03, "point: the largest circle radius", unit="m", above=0.0, maxval=0.1)
    max_point_turns: float = option(5.0, "point: the most turns of the circle", minval=0.25, maxval=20.0)
    default_map_size: tuple = option((0.1, 0.1), "map: the region's x and y extent (centred below the TCP)",
                                     unit="m", minval=0.005, maxval=2.0)
    max_map_size: float = option(1.0, "map: the largest extent, per side", unit="m", above=0.0, maxval=2.0)
    default_map_depth: float = option(0.1, "map: a probe descends at most this far below the start height",
                                      unit="m", above=0.0, maxval=1.0)
    max_map_depth: float = option(0.4, "map: the deepest descent a map may ask", unit="m", above=0.0, maxval=1.0)
    max_map_points: int = option(400, "map: the most grid points (rows x cols)", minval=1, maxval=10000)
    default_home_joint_speed_deg_s: float = option(10.0, "home: the fastest joint's speed (the TCP stays under "
                                                         "max_speed)", unit="deg/s", minval=1.0, maxval=90.0)
    max_home_joint_speed_deg_s: float = option(20.0, "home: the fastest joint speed a task may ask", unit="deg/s",
                                               minval=1.0, maxval=90.0)

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
        checks = {v.name: v.self_check for v in task_verbs_registry.discover().values()}
        control = {v: {"action": "stop"} if v == "record" else {} for v in CONTROL_VERBS}
        for verb, required in {**checks, **control}.items():
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
        limits = read_options(cls, section)
        for key in ("min_speed", "default_speed"):        # bounded by max_speed as read
            if getattr(limits, key) > limits.max_speed:
                raise section.error(key, f"{getattr(limits, key)} is above the maximum {limits.max_speed}")
        return limits


# The limits key that holds each field's default.
DEFAULT_KEYS = {"distance": "default_probe_distance", "probe_distance": "default_probe_distance",
                "joint_speed_deg_s": "default_home_joint_speed_deg_s", "radius": "default_point_radius",
                "depth": "default_map_depth", "size": "default_map_size",
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
            shown = ", ".join(f"{float(x):g}" for x in default)
            raise CommandError(OUT_OF_LIMITS, f"{name}: the configured default [{shown}] {unit} is outside "
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


def _field(obj: dict, f: Field, limits: Limits, verb: str):
    """One field of a task verb (tecdard.verbs.Field), converted and checked; its default when absent."""
    default = f.resolve("default", limits)
    if default is REQUIRED:
        default = None
    lo, hi = f.resolve("lo", limits), f.resolve("hi", limits)
    if f.kind == "number":
        return _number(obj, f.name, default, lo, hi, f.unit)
    if f.kind == "direction":
        return _direction(obj, f.name, default)
    if f.kind == "numbers":
        return _numbers(obj, f.name, default, f.n, lo, hi, f.unit)
    v = obj.get(f.name, default)
    if f.name not in obj and f.default is REQUIRED:
        raise CommandError(MISSING_FIELD, f"{f.name}: required field is missing")
    if f.kind == "choice":
        if not isinstance(v, str) or v not in f.choices:
            expected = " or ".join(f'"{c}"' for c in f.choices)
            raise CommandError(BAD_TYPE, f"{f.name}: expected {expected}, got {show(v)}")
        return v
    if f.kind == "bool":
        if not isinstance(v, bool):
            raise CommandError(BAD_TYPE, f"{f.name}: expected true or false, got {show(v)}")
        return v
    if f.kind == "int_choice":
        if not is_number(v) or v not in f.choices:
            raise CommandError(BAD_TYPE, f"{f.name}: expected {' or '.join(str(c) for c in f.choices)}, got {show(v)}")
        return int(v)
    if f.kind == "grid":
        if not isinstance(v, list) or len(v) != 2 or not all(isinstance(x, int) and not isinstance(x, bool) for x in v):
            raise CommandError(BAD_TYPE, f"{f.name}: expected [rows, cols] as two integers, got {show(v)}")
        if min(v) < 1 or v[0] * v[1] > limits.max_map_points:
            raise CommandError(OUT_OF_LIMITS, f"{f.name}: {v[0]} x {v[1]} points is outside the configured limits "
                                              f"(at least 1 x 1, at most {limits.max_map_points} points)")
        return [int(v[0]), int(v[1])]
    raise CommandError(INTERNAL, f"{verb}.{f.name}: unknown field kind {f.kind!r}")


class TaskFields(dict):
    """A task's validated fields (defaults applied), and `given`: those its payload named. A verb whose default
    depends on the daemon's state (rotate's direction after a rotate) tells a given value from a default."""
    given: frozenset = frozenset()


def validate_task(spec: TaskVerb, obj: dict, limits: Limits) -> TaskFields:
    """A task verb's payload against its fields: normalised values, defaults applied."""
    _check_fields(obj, spec.name, tuple(f.name for f in spec.fields))
    out = TaskFields((f.name, _field(obj, f, limits, spec.name)) for f in spec.fields)
    out.given = frozenset(obj)
    return out


def validate(verb: str, obj: dict, limits: Limits) -> dict:
    """Normalised command fields with defaults applied; CommandError on anything wrong."""
    spec = task_verbs_registry.get(verb)
    if spec is not None:
        return validate_task(spec, obj, limits)
    if verb not in CONTROL_VERBS:
        raise CommandError(UNKNOWN_VERB, f"verb: unknown command '{show_name(verb)}' (known: {', '.join(verbs())})")
    if verb in ("stop", "status", "recover"):
        _check_fields(obj, verb, ())
        return {}
    if verb == "record":
        _check_fields(obj, verb, ("action", "label"))
        action, label = obj.get("action"), obj.get("label", "")
        if action is None:
            raise CommandError(MISSING_FIELD, "record: missing field 'action' (start or stop)")
        if action not in RECORD_ACTIONS:
            raise CommandError(BAD_TYPE, f"action: expected 'start' or 'stop', got {show(action)}")
        if not isinstance(label, str) or len(label) > MAX_LABEL_CHARS:
            raise CommandError(BAD_TYPE, f"label: expected a string of at most {MAX_LABEL_CHARS} characters, "
                                         f"got {show(label)}")
        return {"action": action, "label": label}
    if verb in GRIP_VERBS:
        _check_fields(obj, verb, ("force", "width", "speed") if verb == "grasp" else ("width", "speed"))
        # absent fields: the gripper section's (gripper.force_n, width_m or open_width_m, speed_m_s)
        def optional(name: str, lo: float, hi: float, unit: str) -> float | None:
            return _number(obj, name, None, lo, hi, unit) if name in obj else None
        out = {"width_m": optional("width", 0.0, MAX_GRIP_WIDTH_M, "m"),
               "speed_m_s": optional("speed", 0.001, MAX_GRIP_SPEED_M_S, "m/s")}
        if verb == "grasp":
            out["force_n"] = optional("force", 0.1, MAX_GRIP_FORCE_N, "N")
        return out
    _check_fields(obj, verb, ("task",))
    task = obj.get("task")
    if task is not None and (not isinstance(task, str) or len(task) > MAX_TASK_ID_CHARS):
        raise CommandError(BAD_TYPE, f"task: expected a task id string (at most {MAX_TASK_ID_CHARS} "
                                     f"characters), got {show(task)}")
    return {"task": task}
