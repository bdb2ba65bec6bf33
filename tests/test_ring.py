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
