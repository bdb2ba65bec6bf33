"""The onset trigger in the running daemon (issue 34): tasks in a row on the simulator, recording on,
give one contact onset per contact episode and one recording per task, and the daemon's own stops
and rests give none: no idle capture. benchmarks/onset_live.py runs the same with 20 of each verb."""
import time

import numpy as np
import pytest

from tests.test_home import until_idle

ROUNDS = 3                     # of each verb here; 20 in benchmarks/onset_live.py
TASK_TIMEOUT_S = 60.0
REST_S = 3.0                   # at rest after the tasks, the trigger armed: nothing may fire
TICK_S = 0.02


def run_rounds(d, tasks: list[tuple[str, dict]], rounds: int) -> list[tuple[str, str, dict]]:
    """Each task of `tasks`, then `home` with a fresh world, `rounds` times: (verb, task id, end event)."""
    done = []
    for _ in range(rounds):
        for verb, params in tasks + [("home", {"reset_world": True})]:
            until_idle(d.client)
            reply = d.client.command(verb, params)
            assert reply["ok"], reply
            ev = d.client.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
            assert ev["kind"] == "task_done", f"{verb}: {ev.get('error')}\n{d.log()[-2000:]}"
            done.append((verb, reply["task"], ev))
    until_idle(d.client)
    return done


def recorded(rec_dir, done, timeout_s: float = 20.0) -> tuple[dict, list]:
    """(task id -> its recordings, idle captures), once every task's recording is written."""
    deadline = time.monotonic() + timeout_s
    while True:
        files = sorted(p.name for p in rec_dir.glob("*.npz"))
        per_task = {task: [f for f in files if task in f] for _, task, _ in done}
        idle = [f for f in files if "-idle" in f]
        if all(per_task.values()) or time.monotonic() > deadline:
            return per_task, idle
        time.sleep(0.2)


def check_counts(d, rec_dir, done, episodes: dict) -> None:
    """One onset per contact episode (episodes: verb -> onsets each of its tasks begins), none else;
    one recording per task; no idle capture; the onsets of a task within it."""
    time.sleep(REST_S)
    onsets = [e for e in d.client.event_log if e["kind"] == "contact_onset"]
    expected = sum(episodes.get(verb, 0) for verb, _, _ in done)
    summary = [(e["t"], e.get("trigger"), e["commanded"]) for e in onsets]
    assert len(onsets) == expected, summary
    started = {e["task"]: e["t"] for e in d.client.event_log if e["kind"] == "task_started"}
    ended = {e["task"]: e["t"] for e in d.client.event_log if e["kind"] in ("task_done", "task_failed")}
    for verb, task, _ in done:
        # a commanded onset is the tick's time at the task's first step, a hair before its start event's
        inside = [e for e in onsets if started[task] - TICK_S <= e["t"] <= ended[task]]
        assert len(inside) == episodes.get(verb, 0), (verb, task, started[task], ended[task], summary)
    # a capture opens on a contact onset: one per task with an episode, none for a home
    per_task, idle = recorded(rec_dir, [x for x in done if episodes.get(x[0], 0)])
    assert idle == [], idle
    assert all(len(v) == 1 for v in per_task.values()), per_task


@pytest.mark.slow
def test_probes_and_rotates_in_a_row_give_one_onset_each_and_no_idle_capture(make_daemon, tmp_path):
    rec_dir = tmp_path / "recordings"
    d = make_daemon(**{"record.enabled": True, "record.dir": str(rec_dir)})
    done = run_rounds(d, [("probe", {}), ("rotate", {"angle_deg": 5.0})], ROUNDS)
    turned = [ev["result"]["sim"]["angle_deg"] for verb, _, ev in done if verb == "rotate"]
    assert all(4.0 < a < 8.0 for a in turned), turned             # measured 6.8-6.9 deg: the brake runs on
    check_counts(d, rec_dir, done, {"probe": 1, "rotate": 1})


@pytest.mark.slow
def test_approaches_and_points_in_a_row_give_one_onset_each_and_no_idle_capture(make_daemon, tmp_path):
    """A block held nearly level comes down onto a table: the approach's onset is its impact, on the
    accelerometer, with the arm's own start and the stop after the block has turned not taken for one."""
    tool_m, tilt = 0.12, np.radians(10.0)
    tip_tcp = [float(tool_m * np.cos(tilt)), 0.0, float(tool_m * np.sin(tilt))]
    table = float(0.487 - tool_m * np.sin(tilt) - 0.012)
    rec_dir = tmp_path / "recordings"
    d = make_daemon(**{"record.enabled": True, "record.dir": str(rec_dir), "sim.hinge": ...,
                       "sim.pivot": {"tip_in_tcp": tip_tcp, "table_height": table, "edge_x": 1.0}})
    done = run_rounds(d, [("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                        "stop_angle_deg": 3.0})], ROUNDS)
    onsets = [e for e in d.client.event_log if e["kind"] == "contact_onset"]
    # each at the impact: the block's edge meets the table 12 mm down
    assert all(e["trigger"] == "accel" and abs(e["p_tcp"][2] - (0.487 - 0.012)) < 0.003 for e in onsets), onsets
    check_counts(d, rec_dir, done, {"approach": 1})


IMPACTS = 20
IMPACT_GAP_S = 1.8             # a knock, the contact's rest (control.contact_rest_s, 1 s), the trigger re-armed


def knock(d, stream) -> list[dict]:
    """Once the daemon has no fault (the board's stream has warmed the trigger), IMPACTS knocks IMPACT_GAP_S apart
    on `stream` (sim.board.StreamThread); the events the daemon published."""
    deadline = time.monotonic() + 20.0
    while d.client.command("status")["state"]["faults"]:
        assert time.monotonic() < deadline, d.log()[-2000:]
        time.sleep(0.1)
    time.sleep(1.0)
    for _ in range(IMPACTS):
        stream.impact()
        time.sleep(IMPACT_GAP_S)
    time.sleep(1.5)
    return list(d.client.event_log)


@pytest.mark.slow
def test_knocks_on_an_idle_arm_are_one_onset_each(tmp_path):
    """Issue 51 item 4: with no task, only a task's end released a contact episode, and the trigger never re-armed:
    six knocks 3 s apart on an idle daemon with a serial board gave one onset. Now an idle contact ends once the
    arm and the fingertip have rested control.contact_rest_s (`contact_released`, reason rest) and the next knock
    is an onset of its own: 20 knocks, 20 onsets, 20 releases."""
    from tecdard.sim.board import Board, PtyDevice, StreamThread
    from tests.conftest import DaemonProcess, daemon_config
    device = PtyDevice(tmp_path / "ttyIMU")
    stream = StreamThread(device, Board()).start()
    d = DaemonProcess(tmp_path, daemon_config(**{"imu.source": "serial", "imu.serial": {"port": str(device.link)}}))
    try:
        events = knock(d, stream)
    finally:
        d.close()
        stream.join()
        device.close()
    onsets = [e for e in events if e["kind"] == "contact_onset"]
    released = [e for e in events if e["kind"] == "contact_released"]
    assert len(onsets) == IMPACTS, [(e["kind"], e.get("t")) for e in events if "contact" in e["kind"]]
    faults = [(e["code"], e["message"]) for e in events if e["kind"] == "fault"]
    assert len(released) == IMPACTS and all(e["reason"] == "rest" for e in released), \
        ([(e["reason"], round(e["t"] - e["onset_t"], 3)) for e in released], faults)
    assert all(not e["commanded"] for e in onsets)
    # each release follows its own onset by about the rest (1 s; the idle estimator's 100 ms batches add to it)
    for onset, release in zip(onsets, released):
        assert release["onset_t"] == onset["t"] and 0.9 <= release["t"] - onset["t"] <= IMPACT_GAP_S, (onset, release)
