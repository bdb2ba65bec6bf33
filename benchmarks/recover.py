"""`recover` on each backend (issue 52): a recovery's timeline; writes benchmarks/recover.md.

    python -m benchmarks.recover [--runs N]

- UR: the fake controller whose arm is our simulator (the paper cutter, the board on a pty), through ur-rtde: a
  rotate, a protective stop raised on the controller mid-arc, then `recover` at once (UR's 5 s rule makes it
  wait), then a rotate;
- Franka: franky-sim with the board on a pty: an injected joint reflex at rest, `recover` at once (franky's error
  recovery, before the daemon's own after its 0.5 s back-off), then an approach;
- the simulated arm: an approach onto the table with `sim.robot.protective_stop_force_n` at 1 N; `release` (the
  tool held against the table), `recover`, then `home`.
Times are from the stop's `fault` event (the daemon's clock): to `recover`'s reply, and to the next task's
acceptance. Nothing here ran on a real arm; the figures are the fakes' and this machine's.
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.onset_live import scene  # noqa: E402
from tests.conftest import DaemonProcess, daemon_config  # noqa: E402
from tests.fakes.fake_ur import wait_for  # noqa: E402

OUT = ROOT / "benchmarks" / "recover.md"


def timeline(d, code: str, after_fault, next_task) -> dict:
    """Wait for the fault `code`, run `after_fault(d)` (a person's act, or nothing), `recover`, then
    `next_task(d)` (its reply); times from the fault's event."""
    ev = d.client.wait_event(("fault",), None, 30.0)
    while ev["code"] != code:
        ev = d.client.wait_event(("fault",), None, 30.0)
    t_fault = ev["t"]
    after_fault(d)
    sent = time.monotonic()
    reply = d.client.command("recover", {}, timeout=30.0)
    replied = time.monotonic()
    assert reply.get("ok"), reply
    task = next_task(d)
    accepted = time.monotonic()
    assert task.get("ok"), task
    return {"recover_s": replied - sent, "fault_to_recovered_s": replied - t_fault,
            "fault_to_task_s": accepted - t_fault, "steps": reply["steps"]}


def ur_run(tmp: pathlib.Path) -> dict:
    from tests.test_ur_rotate import cutter_rig
    with cutter_rig(tmp) as (fake, d):
        reply = d.client.command("rotate", {"angle_deg": 30.0})
        assert reply["ok"], reply
        assert wait_for(lambda: abs(fake.truth().handle_angle_rad) > 0.09, 30.0)
        fake.set(safety_status_bits=1 << 2, safety_mode=3)
        return timeline(d, "robot_protective_stop", lambda d: None,
                        lambda d: d.client.command("rotate", {"angle_deg": 10.0}))


def franka_run(tmp: pathlib.Path) -> dict:
    from tecdard.sim.board import Board, PtyDevice, StreamThread
    from tests.test_daemon_franka import franka_with_control
    device = PtyDevice(tmp / "ttyIMU")
    streamer = StreamThread(device, Board()).start()
    try:
        with franka_with_control(tmp / "franka", str(device.link)) as (control, _srv, d):
            assert wait_for(lambda: d.client.command("status")["state"]["faults"] == [], 10.0)
            control.write_text("reflex")
            return timeline(d, "robot_reflex", lambda d: None,
                            lambda d: d.client.command("approach", {"direction": [0.0, 0.0, -1.0],
                                                                    "max_distance": 0.01}))
    finally:
        streamer.join()
        device.close()


def sim_run(tmp: pathlib.Path) -> dict:
    d = DaemonProcess(tmp, daemon_config(**{"sim.robot.protective_stop_force_n": 1.0, **scene("table")}))
    try:
        reply = d.client.command("approach", {"direction": [0.0, 0.0, -1.0], "speed": 0.02, "max_distance": 0.08,
                                              "stop_angle_deg": 5.0})
        assert reply["ok"], reply
        return timeline(d, "robot_protective_stop", lambda d: d.client.command("release", {}, timeout=10.0),
                        lambda d: d.client.command("home", {"reset_world": True}))
    finally:
        d.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per backend (default 2)")
    args = ap.parse_args()
    lines = ["# `recover` on each backend (issue 52)", "",
             f"`python -m benchmarks.recover --runs {args.runs}`: medians [min, max] over the runs, s, from the stop's "
             "`fault` event. Against our protocol fakes and the simulator: nothing here ran on a real arm.", "",
             "| backend | what stopped it | `recover` took | fault to recovered | fault to the next task accepted | "
             "steps |", "|---|---|---|---|---|---|"]
    for name, what, run in (("UR (fake controller, ur-rtde)", "protective stop mid-rotate", ur_run),
                            ("Franka (franky-sim, franky)", "joint reflex at rest", franka_run),
                            ("simulated arm", "protective stop: 1 N on the table (then `release`)", sim_run)):
        got = []
        for k in range(args.runs):
            with tempfile.TemporaryDirectory() as tmp:
                got.append(run(pathlib.Path(tmp)))

        def fmt(key: str) -> str:
            v = [g[key] for g in got]
            return f"{statistics.median(v):.2f} [{min(v):.2f}, {max(v):.2f}]"
        lines.append(f"| {name} | {what} | {fmt('recover_s')} | {fmt('fault_to_recovered_s')} | "
                     f"{fmt('fault_to_task_s')} | {'; '.join(got[-1]['steps'])} |")
        print(lines[-1], flush=True)
    OUT.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
