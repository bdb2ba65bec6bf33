"""Sample ring: batches in order, wrap-around, overwrite accounting, blocking pop."""
import threading

import numpy as np

from tecdard.drivers.ring import SampleRing


def batch(t0, n):
    t = t0 + np.arange(n, dtype=float)
    return t, np.tile(t[:, None], (1, 3)), -np.tile(t[:, None], (1, 3))


def test_fifo_order_across_wrap():
    ring = SampleRing(100)
    got = []
    for k in range(10):
        ring.push(*batch(37 * k, 37))
        got.append(ring.pop(1000, timeout=0))
    out = np.vstack(got)
    assert np.array_equal(out[:, 0], np.arange(370, dtype=float))
    assert np.array_equal(out[:, 1], out[:, 0]) and np.array_equal(out[:, 4], -out[:, 0])
    assert ring.overwritten == 0


def test_overflow_keeps_newest_and_counts():
    ring = SampleRing(64)
    ring.push(*batch(0, 100))
    assert ring.overwritten == 36
    out = ring.pop(1000, timeout=0)
    assert np.array_equal(out[:, 0], np.arange(36, 100, dtype=float))
    assert ring.last_t == 99.0


def test_pop_waits_for_data():
    ring = SampleRing(64)
    th = threading.Timer(0.05, lambda: ring.push(*batch(0, 5)))
    th.start()
    out = ring.pop(10, timeout=5.0)
    th.join()
    assert len(out) == 5
    assert len(ring.pop(10, timeout=0.0)) == 0


def test_pop_waits_for_a_minimum_batch_and_gives_what_there_is_at_the_timeout():
    ring = SampleRing(256)

    def produce():
        for k in range(4):
            ring.push(*batch(8 * k, 8))       # 8-sample packets, as the board sends them
            threading.Event().wait(0.02)

    th = threading.Thread(target=produce)
    th.start()
    out = ring.pop(100, timeout=5.0, min_n=20)
    th.join()
    assert len(out) >= 20 and np.array_equal(out[:, 0], np.arange(len(out), dtype=float))
    rest = ring.pop(100, timeout=0.05, min_n=100)    # fewer than asked: returned after the timeout
    assert len(out) + len(rest) == 32


def test_a_sample_beyond_the_alarm_ends_a_long_wait_and_one_within_it_does_not():
    """Issue 53 item 2: a consumer waiting for a rest batch (here 2000 samples, up to 10 s) is woken by the first
    push holding an accelerometer sample alarm_m_s2 or more from the stream's level, with what has come."""
    ring = SampleRing(4096)
    ring.alarm_m_s2 = 1.0
    n, zeros = 80, np.zeros((80, 3))
    t = np.arange(n) / 6667.0
    level = np.tile([0.0, 0.0, 9.81], (n, 1))
    ring.push(t, zeros, level)
    got = {}
    consumer = threading.Thread(target=lambda: got.update(out=ring.pop(4096, timeout=10.0, min_n=2000)))
    consumer.start()
    ring.push(t + 0.012, zeros, level + [0.5, 0.0, 0.0])     # a step within the alarm: the wait goes on
    consumer.join(0.2)
    assert consumer.is_alive() and ring.alarms == 0
    knock = level.copy()
    knock[40] += [0.0, -3.0, 0.0]
    ring.push(t + 0.024, zeros, knock)
    consumer.join(5.0)
    assert not consumer.is_alive() and ring.alarms == 1
    assert len(got["out"]) == 3 * n                          # all that had come, long before the 2000
    ring.alarm_m_s2 = float("inf")                           # off: a knock wakes nobody
    ring.push(t + 0.036, zeros, knock)
    assert ring.alarms == 1


def test_a_stream_that_strays_from_its_level_raises_its_own_alarm():
    """A moving, vibrating arm's raw accelerometer strays from its level by more than the trigger's threshold all
    the time: the alarm then stands at 1.5 times the spread it has shown lately, so that it does not ring on every
    packet (the trigger judges what the arm's motion and vibration leave); an impact beyond that still rings."""
    ring = SampleRing(65536)
    ring.alarm_m_s2 = 0.3
    n, zeros = 17, np.zeros((17, 3))
    for k in range(400):                                     # 1 s of 40 Hz vibration, 2 m/s^2, in 2.5 ms pushes
        t = (k * n + np.arange(n)) / 6667.0
        accel = np.zeros((n, 3)) + [0.0, 0.0, 9.81]
        accel[:, 0] += 2.0 * np.sin(2 * np.pi * 40.0 * t)
        ring.push(t, zeros, accel)
    vibrating = ring.alarms
    assert vibrating <= 2                                    # its first swings, before it had a spread
    t = (400 * n + np.arange(n)) / 6667.0
    within = np.zeros((n, 3)) + [0.0, 0.0, 9.81]
    within[5, 1] += 2.5                                      # beyond the alarm, within 1.5 x the spread
    ring.push(t, zeros, within)
    assert ring.alarms == vibrating
    beyond = np.zeros((n, 3)) + [0.0, 0.0, 9.81]
    beyond[5, 1] += 6.0
    ring.push(t + n / 6667.0, zeros, beyond)
    assert ring.alarms == vibrating + 1
