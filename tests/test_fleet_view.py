"""Issue 50 item 4: one robot's malformed state never breaks `fleet status` or `fleet watch`. Each field is read
on its own (a bad one is `?` in that robot's row only), non-finite numbers become null, and a robot's control
characters never reach the operator's terminal."""
import json
import time
import types

from tecdard.cli.fleet_status import BAD, FleetView, RobotSeen, json_rows, row, table

GOOD = {"mode": "busy", "task": {"id": "r1", "kind": "rotate", "phase": "arc"}, "faults": [],
        "contact": {"p": [0.5, 0.0, 0.2]}, "imu": {"rate_hz": 6667.0}, "control": {"overruns": 0}}


def seen(state) -> RobotSeen:
    return RobotSeen(state=state, state_at=time.monotonic(), alive=True)


def test_a_malformed_robot_is_marked_in_its_own_row_and_the_others_stand():
    now = time.monotonic()
    hostile = {"mode": "\x1b[2J", "task": {"kind": "rotate"}, "faults": [{"code": 7}, {"code": "\x1b]0;pwned\x07"}],
               "contact": {"p": [float("nan"), 0.0, 0.1]}, "imu": 12, "control": {"overruns": -3}}
    rows = [row("good", seen(GOOD), now), row("evil\x1b[31m", seen(hostile), now), row("void", seen("x"), now)]
    good, evil, void = rows
    assert good["bad"] == [] and good["task"] == {"kind": "rotate", "phase": "arc"} and good["imu_rate_hz"] == 6667.0
    assert set(evil["bad"]) == {"mode", "task", "faults", "contact", "imu", "overruns"}
    assert evil["faults"][0] == BAD and "\x1b" not in evil["faults"][1] and "\\u001b" in evil["faults"][1]
    assert void["mode"] is None and void["bad"] == []                  # a state that is no object: nothing to show
    text = table(rows)
    assert "\x1b" not in text and "\x07" not in text
    evil_line = next(line for line in text.splitlines() if line.startswith("evil"))
    assert evil_line.split()[1:3] == [BAD, BAD]                          # mode and task
    assert "rotate arc" in next(line for line in text.splitlines() if line.startswith("good"))
    out = json.dumps(json_rows(rows), allow_nan=False)                   # strict JSON: no NaN anywhere
    back = json.loads(out)
    assert back[1]["mode"] is None and back[1]["contact_p"] is None and back[1]["faults"][0] is None
    assert back[0]["contact_p"] == [0.5, 0.0, 0.2]


def test_a_message_that_is_not_a_json_object_leaves_the_robot_silent_not_the_view_dead():
    def sample(payload: bytes):
        return types.SimpleNamespace(payload=types.SimpleNamespace(to_bytes=lambda: payload))
    for payload in (b"\xff\xfe", b"not json", b"[1, 2]", b"[" * 100 + b"]" * 100):
        assert FleetView._decoded(sample(payload)) is None, payload
    state = FleetView._decoded(sample(b'{"mode": "idle", "imu": {"rate_hz": NaN}}'))
    assert state == {"mode": "idle", "imu": {"rate_hz": None}}


def test_a_lost_board_shows_in_the_fleet_view_with_how_long_ago():
    """Issue 50 item 12: an unplugged board showed as imu_stale with a frozen age. The state's imu.lost_s (how
    long ago the port was lost) makes the link `imu_disconnected 12 s`, and is in --json; a bad one is `?`."""
    now = time.monotonic()
    lost = {**GOOD, "faults": [{"code": "imu_stale", "message": "..."}, {"code": "imu_disconnected", "message": "..."}],
            "imu": {"rate_hz": 0.0, "lost_s": 12.3}}
    r = row("arm", seen(lost), now)
    assert r["link"] == "imu_disconnected 12 s" and r["imu_lost_s"] == 12.3 and r["bad"] == [], r
    assert json_rows([r])[0]["imu_lost_s"] == 12.3
    bad = row("arm", seen({**lost, "imu": {"rate_hz": 0.0, "lost_s": float("nan")}}), now)
    assert bad["link"] == "imu_stale" or bad["link"].startswith("imu_"), bad
    assert "imu" in bad["bad"] and bad["imu_lost_s"] == BAD
    assert row("arm", seen(GOOD), now)["imu_lost_s"] is None
