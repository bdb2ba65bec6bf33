"""Issue 37: each OS thread's CPU share and wake-up wait, as `status` reports them."""
import threading
import time

import numpy as np
import pytest

from tecdard.drivers.ring import SampleRing
from tecdard.runtime import threads
from tecdard.host import name_os_thread
from tecdard.cli.show import status_lines


def test_wake_stats_keep_the_largest_wait_of_the_last_seconds():
    w = threads.WakeStats()
    assert w.max_ms(100.0) is None
    w.note(0.0004, 100.1)
    w.note(0.0021, 100.5)
    w.note(0.0009, 101.2)
    assert w.max_ms(101.3) == 2.1
    assert w.max_ms(100.5 + threads.WAKE_WINDOW_S + 1.0) == 0.9      # the second with 2.1 ms has left the window
    assert w.max_ms(200.0) is None


@pytest.mark.slow
def test_thread_usage_measures_a_busy_named_thread(tmp_path):
    """A thread that spins for a second shows as itself, near a whole core; a sleeping one near zero."""
    stop = threading.Event()

    def spin():
        name_os_thread("spinner")
        x = 0
        while not stop.is_set():
            x += 1

    def sleeper():
        name_os_thread("sleeper")
        stop.wait()

    workers = [threading.Thread(target=spin), threading.Thread(target=sleeper)]
    for t in workers:
        t.start()
    wake = threads.WakeStats()
    wake.note(0.003, time.monotonic())
    usage = threads.ThreadUsage({"spinner": wake})
    try:
        t0 = time.monotonic()
        usage.sample(t0)
        usage.sample(t0 + 0.1)                    # within SAMPLE_EVERY_S: not read again
        assert usage.snapshot() == {}
        time.sleep(1.2)
        usage.sample(time.monotonic())
        snap = usage.snapshot()
    finally:
        stop.set()
        for t in workers:
            t.join()
    assert snap["spinner"]["cpu_pct"] > 30.0 and snap["spinner"]["wake_ms_max"] == 3.0
    assert snap["sleeper"]["cpu_pct"] < 5.0 and "wake_ms_max" not in snap["sleeper"]
    assert list(snap)[0] == "spinner"             # the busiest first
    lines = status_lines({"mode": "idle", "threads": snap})
    assert any(line.split()[:4] == ["spinner", f"{snap['spinner']['cpu_pct']:.1f}", "%,", "waited"]
               for line in lines), lines


def test_a_missing_proc_is_no_threads(tmp_path):
    assert threads.read_threads_cpu_s(str(tmp_path / "none")) == {}


def test_the_ring_wakes_its_consumer_once_the_batch_is_there_and_times_the_wait():
    """The estimator waits for a batch: pushes short of it do not wake it; the push that completes it does,
    and the wait from that push to the consumer running is noted."""
    ring = SampleRing(1024)
    ring.wake = threads.WakeStats()
    got = []
    waiting = threading.Event()

    def consume():
        waiting.set()
        got.append(ring.pop(100, 5.0, 40))

    t = threading.Thread(target=consume)
    t.start()
    waiting.wait()
    time.sleep(0.05)
    for i in range(5):                            # 8-sample packets, as the board sends them
        ring.push(np.arange(8) + 8.0 * i, np.zeros((8, 3)), np.zeros((8, 3)))
        time.sleep(0.01)
        assert not got if i < 4 else True
    t.join(5.0)
    assert len(got) == 1 and len(got[0]) == 40 and got[0][-1, 0] == 39.0
    wait_ms = ring.wake.max_ms(time.monotonic())
    assert wait_ms is not None and 0.0 <= wait_ms < 5000.0


@pytest.mark.slow
def test_a_running_daemons_status_names_its_threads(shared_daemon):
    """`status` of a live daemon: each named thread's share of a core, the wake-up waits of the control
    tick and the estimator, and the CLI's table of them."""
    import subprocess
    import sys
    from tests.conftest import ROOT
    time.sleep(threads.SAMPLE_EVERY_S * 2.5)
    st = shared_daemon.client.command("status")["state"]
    rows = st["threads"]
    # (the simulator's link reader feeds proprioception itself: no thread of its own)
    assert {"control", "estimator", "imu-acquisition", "sim-link", "recorder"} <= set(rows), rows
    assert "proprioception" not in rows
    assert all(0.0 <= row["cpu_pct"] <= 200.0 for row in rows.values())
    for name in ("control", "estimator"):
        assert isinstance(rows[name]["wake_ms_max"], float) and rows[name]["wake_ms_max"] >= 0.0, rows[name]
    cli = subprocess.run([sys.executable, "-m", "tecdard", "status", "--connect", shared_daemon.endpoint,
                          "--robot", "sim"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert cli.returncode == 0, cli.stderr
    assert "threads" in cli.stdout and "control" in cli.stdout and "waited up to" in cli.stdout, cli.stdout


def test_the_ring_tells_the_producer_how_far_the_consumers_batch_is_and_a_smaller_want_wakes_both():
    ring = SampleRing(1024)
    assert ring.shortfall() == 1                                  # nobody has asked yet: any sample is wanted
    assert len(ring.pop(100, 0.0, 40)) == 0                       # asked for 40, none there
    ring.push(np.arange(8.0), np.zeros((8, 3)), np.zeros((8, 3)))
    assert ring.shortfall() == 32
    got = []
    t = threading.Thread(target=lambda: got.append(ring.pop(100, 5.0, 40)))
    t.start()
    time.sleep(0.05)
    assert not got                                                # 8 of 40: still waiting
    ring.hurry.clear()
    ring.lower_want(8)                                            # a task started: smaller batches
    t.join(5.0)
    assert len(got) == 1 and len(got[0]) == 8 and ring.hurry.is_set()
    assert ring.shortfall() == 8


class PacedSource:
    """8-sample packets at 6667 Hz into a port buffer; `read` returns all that has arrived (as the
    serial driver does), waiting for the next packet when none has. Counts its reads."""
    odr_hz = 6667.0

    def __init__(self, packets: int):
        self.t0 = time.monotonic()
        self.packets, self.sent, self.reads = packets, 0, 0

    def read(self, timeout: float = 0.05):
        due = min(int((time.monotonic() - self.t0) * self.odr_hz / 8), self.packets)
        if due == self.sent:
            if self.sent == self.packets:
                time.sleep(timeout)
                return None
            time.sleep(max(self.t0 + (self.sent + 1) * 8 / self.odr_hz - time.monotonic(), 0.0))
            due = self.sent + 1
        n = 8 * (due - self.sent)
        t = (np.arange(n) + 8 * self.sent) / self.odr_hz
        self.sent = due
        self.reads += 1
        return t, np.zeros((n, 3)), np.zeros((n, 3))

    def drain_events(self):
        return []


@pytest.mark.slow
def test_the_acquisition_thread_reads_a_batch_in_a_few_wake_ups_and_loses_nothing():
    """Issue 37: the reader naps until the consumer's batch is nearly complete instead of waking for
    every packet (840 a second from a board); every sample still reaches the consumer, in order."""
    from tecdard.runtime.messages import Outbox
    from tecdard.runtime.workers import acquisition_loop
    ring, stop = SampleRing(65536), threading.Event()
    src = PacedSource(packets=200)                                # 0.24 s of a board's stream
    th = threading.Thread(target=acquisition_loop, args=(src, ring, stop, Outbox(16)))
    th.start()
    got = []
    try:
        while sum(map(len, got)) < 1600:
            batch = ring.pop(4096, 1.0, 134)                      # the estimator's batch at rest (20 ms)
            assert len(batch), "the consumer starved"
            got.append(batch)
    finally:
        stop.set()
        th.join(5.0)
    t = np.concatenate(got)[:, 0]
    assert np.array_equal(t, np.arange(1600) / 6667.0)
    assert src.reads < 200 / 2, src.reads                         # 58 here, for 200 packets


def test_with_rt_priority_the_threads_the_tick_waits_on_run_less_nice():
    """raise_gil_threads: the GIL's other holders at nice -10 where the host allows it, else one reason."""
    import os
    import threading
    from tecdard.host import name_os_thread
    from tecdard.runtime.realtime import raise_gil_threads
    ready, done = threading.Event(), threading.Event()
    tid = []

    def body():
        name_os_thread("estimator")
        tid.append(threading.get_native_id())
        ready.set()
        done.wait(10.0)
    th = threading.Thread(target=body, daemon=True)
    th.start()
    ready.wait(5.0)
    main = threading.main_thread().native_id
    before = os.getpriority(os.PRIO_PROCESS, main)
    try:
        problem = raise_gil_threads(nice=-3)
        if problem is None:
            assert os.getpriority(os.PRIO_PROCESS, tid[0]) == -3 and os.getpriority(os.PRIO_PROCESS, main) == -3
        else:
            assert "refused" in problem and "LimitNICE" in problem
    finally:
        done.set()
        th.join(5.0)
        try:
            os.setpriority(os.PRIO_PROCESS, main, before)
        except PermissionError:
            pass


def test_the_estimator_takes_the_commands_given_during_its_wait_before_the_batch_that_ends_it():
    """Issue 53 item 2: the arm's states and the daemon's commands were taken before the estimator's wait, so
    the commands that held an idle arm still were 50-90 ms old when a knock's alarm ended a rest batch's wait,
    and could not decide its onset at once. Now they are taken after the wait: a tick noted while the
    estimator waits reaches the pipeline before the batch the alarm brought, and the alarm (armed from the
    trigger's threshold once it is warm) ends the 100 ms rest wait with what has come."""
    from tecdard.config import Config
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.control.proprio import ProprioSample
    from tecdard.runtime.messages import Outbox
    from tecdard.runtime.workers import EstimatorThread
    pipe = ContactPipeline.from_config(Config({}).section("estimator"), np.eye(3), 6667.0)
    ring = SampleRing(65536)
    est = EstimatorThread(pipe, ring, None, Outbox(64), min_batch=33, commands=True)
    est._follow_odr(6667.0)
    est.set_resting(True)
    order = []
    add_command, process = pipe.add_command, pipe.process
    pipe.add_command = lambda t, qd: (order.append(("command", t)), add_command(t, qd))[1]
    pipe.process = lambda batch: (order.append(("batch", len(batch))), process(batch))[1]
    stop = threading.Event()
    worker = threading.Thread(target=est.run, args=(stop,), daemon=True)
    worker.start()
    try:
        rest = np.tile([0.0, 0.0, 9.81], (8, 1))
        for k in range(170):                                   # 0.2 s of rest in packets: the trigger warms
            t = (8 * k + np.arange(8)) / 6667.0
            if k % 16 == 0:                                    # the arm's states at about 50 Hz, held still
                est.proprio.push(ProprioSample(float(t[0]), np.array([0.3, 0.0, 0.5]), np.zeros(3), np.eye(3),
                                               np.zeros(3)))
            ring.push(t, np.zeros((8, 3)), rest)
            time.sleep(0.0012)
        deadline = time.monotonic() + 5.0
        while ring.alarm_m_s2 == float("inf") and time.monotonic() < deadline:
            time.sleep(0.01)
        assert ring.alarm_m_s2 < 1.0, ring.alarm_m_s2          # armed: half the trigger's threshold
        before = len(order)
        time.sleep(0.03)                                       # the estimator waits for its rest batch
        est.note_command(0.2, np.zeros(6))                     # a tick while it waits
        knock = rest.copy()
        knock[2] += [0.0, 5.0, 0.0]
        ring.push((8 * 170 + np.arange(8)) / 6667.0, np.zeros((8, 3)), knock)
        while not any(kind == "batch" for kind, _ in order[before:]) and time.monotonic() < deadline:
            time.sleep(0.005)
    finally:
        stop.set()
        worker.join(2.0)
    after = order[before:]
    assert ring.alarms >= 1 and after[0] == ("command", 0.2), after[:3]
    assert after[1][0] == "batch" and after[1][1] < 660, after[:3]     # less than the 100 ms rest batch
