"""The acquisition and estimator thread bodies: IMU source -> ring buffer -> contact pipeline."""
from __future__ import annotations

import logging
import queue
import threading
import time

from control.pipeline import ContactPipeline
from drivers.ring import SampleRing

log = logging.getLogger("tecdar.estimator")

POP_MAX_SAMPLES = 4096
POP_TIMEOUT_S = 0.02


def acquisition_loop(source, ring: SampleRing, stop: threading.Event, outbox: queue.Queue | None = None) -> None:
    """Transport only: move timestamped SI samples from the source into the ring, and hand the
    source's events (port lost, port back) to the outbox."""
    drain = getattr(source, "drain_events", None)
    while not stop.is_set():
        chunk = source.read(timeout=0.05)
        if chunk is not None:
            ring.push(*chunk)
        if drain is not None and outbox is not None:
            for ev in drain():
                try:
                    outbox.put_nowait(("event", {"t": time.monotonic(), **ev}))
                except queue.Full:
                    pass


class EstimatorThread:
    """Owns the contact pipeline. It reads proprioception from the robot itself, before each
    batch; the controller's notices (`release`, `arm`, `begin`, ...) arrive on `inbox`;
    estimates leave through the `contact` latest-value slot and the outbox."""

    def __init__(self, pipeline: ContactPipeline, ring: SampleRing, contact, outbox: queue.Queue,
                 robot, model, min_batch: int = 1):
        self.pipeline = pipeline
        self.ring = ring
        # Every proprioception sample, at most a batch late. (Forwarded by the 20 ms control tick,
        # a quarter of the 65 Hz samples never reached the estimator and the rest came up to a tick
        # late, more on a loaded machine: the pipeline then extrapolated the TCP much further.)
        self.robot = robot
        self.model = model               # this thread's own clone (one pin.Data per thread)
        self._proprio_seq = -1
        # Samples to wait for (up to POP_TIMEOUT_S) before a batch. The pipeline's fixed cost is per
        # batch (some fifty numpy calls), and a source delivers a few samples at a time (a 2 ms
        # slice from the simulator, 8-sample packets from the board): the daemon waits for one
        # output period's worth, which costs at most that much latency.
        self.min_batch = min_batch
        self.contact = contact
        self.outbox = outbox
        self.inbox: queue.Queue = queue.Queue(maxsize=1024)
        self.dropped = 0

    def _put(self, item) -> None:
        try:
            self.outbox.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _read_proprio(self) -> None:
        js = self.robot.read_state()
        if js.seq == self._proprio_seq:
            return
        self._proprio_seq = js.seq
        oMtcp, twist = self.model.fk_twist(js.q, js.qd)
        if js.tcp_twist is not None:
            twist = js.tcp_twist          # the robot's own report of its TCP velocity
        self.pipeline.add_proprio(js.t, oMtcp.translation.copy(), twist[:3].copy(), oMtcp.rotation.copy(),
                                  twist[3:].copy())

    def run(self, stop: threading.Event) -> None:
        pipe = self.pipeline
        while not stop.is_set():
            while True:
                try:
                    msg = self.inbox.get_nowait()
                except queue.Empty:
                    break
                if msg[0] == "release":
                    pipe.release()
                elif msg[0] == "arc":
                    pipe.set_arc_following(msg[1])
                elif msg[0] == "arm":
                    pipe.set_trigger_armed(*msg[1:])
                elif msg[0] == "begin":
                    pipe.begin(msg[1])
                elif msg[0] == "hold_bias":
                    pipe.hold_bias(msg[1])
            batch = self.ring.pop(POP_MAX_SAMPLES, POP_TIMEOUT_S, self.min_batch)
            self._read_proprio()
            events, est = pipe.process(batch)
            for ev in events:
                self._put(("event", ev))
            if est is not None:
                self.contact.set(est)
                self._put(("contact", est.to_json()))
