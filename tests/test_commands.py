"""Command validation: every bad payload gets a code and a message naming the field."""
import pytest

from tecdard.api import commands as C

LIMITS = C.Limits(max_speed=0.05, max_rotation_deg=90.0, max_probe_distance=0.02)


def check(verb, payload):
    return C.validate(verb, C.parse_payload(payload), LIMITS)


def test_rotate_defaults_and_normalisation():
    f = check("rotate", '{"angle_deg": 30, "direction": [0, 0, 1.0005]}')
    assert f["angle_deg"] == 30.0
    assert f["speed"] == LIMITS.default_speed
    assert f["probe_distance"] == LIMITS.default_probe_distance
    assert f["strategy"] == "arc"
    assert abs(sum(x * x for x in f["direction"]) - 1.0) < 1e-12


@pytest.mark.parametrize("verb,payload,code,field", [
    ("rotate", "{not json", C.BAD_JSON, "payload"),
    ("rotate", "[1, 2]", C.BAD_JSON, "payload"),
    ("rotate", "{}", C.MISSING_FIELD, "angle_deg"),
    ("rotate", '{"angle_deg": "thirty"}', C.BAD_TYPE, "angle_deg"),
    ("rotate", '{"angle_deg": true}', C.BAD_TYPE, "angle_deg"),
    ("rotate", '{"angle_deg": 500}', C.OUT_OF_LIMITS, "angle_deg"),
    ("rotate", '{"angle_deg": 30, "speed": 2.0}', C.OUT_OF_LIMITS, "speed"),
    ("rotate", '{"angle_deg": 30, "direction": [0, 0, 2]}', C.OUT_OF_LIMITS, "direction"),
    ("rotate", '{"angle_deg": 30, "direction": [0, 1]}', C.BAD_TYPE, "direction"),
    ("rotate", '{"angle_deg": 30, "strategy": "zigzag"}', C.BAD_TYPE, "strategy"),
    ("rotate", '{"angle_deg": 30, "turn_tool": "yes"}', C.BAD_TYPE, "turn_tool"),
    ("rotate", '{"angle_deg": 30, "angle": 3}', C.UNKNOWN_FIELD, "angle"),
    ("probe", '{"distance": 0.5}', C.OUT_OF_LIMITS, "distance"),
    ("cancel", '{"task": 5}', C.BAD_TYPE, "task"),
    ("dance", "{}", C.UNKNOWN_VERB, "dance"),
    ("map", '{"grid": [2, 2], "depth": 5}', C.OUT_OF_LIMITS, "depth"),
    ("approach", "{}", C.MISSING_FIELD, "direction"),
    ("approach", "{\"direction\": [0, 0, -1], \"max_distance\": 5}", C.OUT_OF_LIMITS, "max_distance"),
])
def test_bad_commands(verb, payload, code, field):
    with pytest.raises(C.CommandError) as info:
        check(verb, payload)
    assert info.value.code == code
    assert field in info.value.message
    reply = info.value.reply()
    assert reply["ok"] is False and reply["error"]["code"] == code


def test_nan_is_not_a_number():
    with pytest.raises(C.CommandError) as info:
        C.validate("rotate", {"angle_deg": float("nan")}, LIMITS)
    assert info.value.code == C.BAD_TYPE
