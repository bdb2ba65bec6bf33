"""The live view: a Foxglove WebSocket server (`viz.foxglove`, off by default, loopback by default)
publishing tecdard/foxglove_io.py's channels as the daemon runs.

Fed like the recorder: the estimator thread hands each pass (its IMU batch, the proprioception it
added, its estimate and events) to a bounded queue, the main thread the daemon's events. Overflow
is dropped and counted, and nothing waits. The view's own thread publishes every VIEW_PERIOD_S:
- the IMU as one batch;
- every TCP sample as a transform;
- the newest estimate;
- every event.

With no client connected it only empties its queue. Foxglove Studio connects to
ws://<host>:<port>. The server is foxglove-sdk's (the `viz` extra).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from tecdard.options import option, read_options
from tecdard.runtime.messages import Inbox
from tecdard.runtime.view_gate import ViewerGate, backlog_messages

log = logging.getLogger("tecdar.viz")

VIEW_PERIOD_S = 0.02          # the view publishes at 50 Hz
QUEUE_ITEMS = 2048            # passes and events waiting (10 s of passes)


@dataclass(frozen=True)
class VizParams:
    """The `viz.foxglove` section: the live view, a Foxglove WebSocket server."""
    enabled: bool = option(False, "serve the live view")
    host: str = option("127.0.0.1", "the address it listens on: loopback (another machine: an SSH tunnel, or this "
                                    "host's address)", max_len=253)
    port: int = option(8765, "its TCP port (Foxglove's usual)", minval=1, maxval=65535)
    max_viewers: int = option(4, "viewers at once; more are turned away (503)", minval=1, maxval=64)
    viewer_buffer_mb: float = option(2.0, "what may wait for one viewer; a slow one loses its oldest frames",
                                     unit="MB", minval=0.25, maxval=64.0)

    @classmethod
    def from_config(cls, section) -> "VizParams":
        from tecdard.config import ConfigError
        params = read_options(cls, section)
        if params.enabled:
            try:
                import foxglove  # noqa: F401
            except ImportError:
                raise ConfigError(f"{section.path}.enabled: the live view needs foxglove-sdk: "
                                  "pip install 'tecdar[viz]'") from None
        return params


class LiveView:
    def __init__(self, params: VizParams, R_tcp_imu: np.ndarray, emit=None):
        self.params = params
        self.R_tcp_imu = np.asarray(R_tcp_imu, float)
        self.emit = emit or (lambda kind, **f: None)
        self.inbox = Inbox(QUEUE_ITEMS)
        self.port: int | None = None
        self.gate: ViewerGate | None = None
        self.ready = threading.Event()

    def feed(self, p) -> None:
        """On the estimator thread: never blocks."""
        self.inbox.put(("pass", p))

    def note_event(self, event: dict) -> None:
        self.inbox.put(("event", event))

    def run(self, stop: threading.Event) -> None:
        import foxglove

        from tecdard.recording.foxglove import Channels
        ctx = foxglove.Context()
        buffer_bytes = int(self.params.viewer_buffer_mb * 1e6)
        try:
            # the server on a loopback port of its own, behind the gate (runtime.view_gate)
            server = foxglove.start_server(name="tecdard", host="127.0.0.1", port=0, context=ctx,
                                           message_backlog_size=backlog_messages(buffer_bytes))
        except Exception as exc:
            log.error("viz.foxglove: the live view's server did not start (%s); no live view", _line(exc))
            self.emit("warning", code="viz_unavailable", message="viz.foxglove: the live view's server did not start")
            self.ready.set()
            return
        try:
            self.gate = ViewerGate(self.params.host, self.params.port, server.port, self.params.max_viewers,
                                   buffer_bytes)
        except OSError as exc:            # the port is taken: the daemon runs on without its view
            server.stop()
            log.error("viz.foxglove: cannot serve on %s:%d (%s); no live view", self.params.host, self.params.port,
                      _line(exc))
            self.emit("warning", code="viz_unavailable",
                      message=f"viz.foxglove: cannot serve on {self.params.host}:{self.params.port}")
            self.ready.set()
            return
        self.port = self.gate.port
        gate = threading.Thread(target=self.gate.run, args=(stop,), name="viz-gate", daemon=True)
        gate.start()
        channels = Channels(ctx, origin_s=time.monotonic(), epoch_s=time.time(), arm=False)
        log.info("live view: Foxglove WebSocket server on ws://%s:%d (at most %d viewers, %.1f MB each)",
                 self.params.host, self.port, self.params.max_viewers, self.params.viewer_buffer_mb)
        self.ready.set()
        try:
            t_next = time.monotonic()
            while not stop.is_set():
                t_next += VIEW_PERIOD_S
                self._publish(channels, self.inbox.drain())
                delay = t_next - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                elif delay < -1.0:
                    t_next = time.monotonic()
        finally:
            channels.close()
            gate.join(1.0)
            server.stop()

    def _publish(self, ch, items: list) -> None:
        passes = [x[1] for x in items if x[0] == "pass"]
        events = [x[1] for x in items if x[0] == "event"] + [e for p in passes for e in p.events]
        try:
            batches = [p.batch for p in passes if len(p.batch)]
            if batches and ch.imu.has_sinks():
                b = np.concatenate(batches)
                ch.imu_batch(b[:, 0], b[:, 1:4], b[:, 4:7])
            if ch.tf.has_sinks():
                for p in passes:
                    for sample in p.proprio:
                        ch.tcp(sample.t, sample.p_world, sample.R_world_tcp, self.R_tcp_imu)
            est = next((p.estimate for p in reversed(passes) if p.estimate is not None), None)
            if est is not None and ch.contact_ch.has_sinks():
                ch.contact(est.t, est.p, est.cov, est.axis)
            if ch.events.has_sinks():
                for ev in events:
                    t = ev.get("t")
                    ch.event(float(t) if isinstance(t, (int, float)) else time.monotonic(), ev)
        except Exception:                # a view's failure costs a frame, never the daemon
            log.exception("live view: a frame was lost")


def _line(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
