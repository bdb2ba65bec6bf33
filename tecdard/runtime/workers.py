"""The acquisition, proprioception and estimator thread bodies: IMU source -> ring buffer -> contact
pipeline, and the robot's proprioception -> a ring of its own -> the pipeline."""
from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

from tecdard.control.mount_fit import MountMonitor
from tecdard.control.pipeline import ContactPipeline, EstimatorDirective
from tecdard.control.proprio import ProprioSample
from tecdard.drivers.imu_source import ImuSource
from tecdard.drivers.ring import SampleRing
from tecdard.runtime.messages import DropOldestRing, LatestValue, Outbox
from tecdard.runtime.capture import Pass

log = logging.getLogger("tecdar.estimator")

POP_MAX_SAMPLES = 4096
POP_TIMEOUT_S = 0.02
# A batch's wait ends this much after its samples are due at the source's rate (they come late only
# when the source stalls): a rest batch (20 ms) must not time out just short of complete.
POP_TIMEOUT_MARGIN = 1.5
# Between contact episodes the estimator thread waits for this many output periods of samples (10 ms):
# the onset trigger's cost is per batch (some sixty numpy calls, 0.1-0.3 ms), and an onset found
# 5 ms later is still within the control tick (20 ms); its time stamp is the sample's.
IDLE_BATCH_FACTOR = 2
# While no task runs (the arm holds still and nothing waits on the trigger), 100 ms batches: a tenth
# of the passes (a pass's fixed cost, and the wake-ups of this thread and the reader, were the daemon's
# largest share of a core at rest). A task's start cuts the wait short (EstimatorThread.set_resting),
# so the trigger of a task is as quick as before; an uncommanded touch at rest is dated by its own
# sample either way, and found up to 95 ms later. A live view shows the stream to a person: with one,
# the rest batch is VIEWED_REST_BATCH_FACTOR (20 ms), not a 10 Hz jerk.
REST_BATCH_FACTOR = 20
VIEWED_REST_BATCH_FACTOR = 4
# The acquisition thread need not wake for every packet (a board's comes every 1.2 ms): until the
# estimator's batch is nearly complete nothing waits for the samples, and the port or the pipe holds
# them. It naps until NAP_MARGIN_S before the batch can be complete (at most NAP_MAX_S), then reads
# as they come, so the batch is handed over as soon as before. The kernel's tty buffer holds some
# 0.7 s of a board's stream; the clock sync's lower envelope takes the packets read as they came.
# NAP_MAX_S keeps the ring's newest sample well inside the stale-IMU limit (safety.imu_stale_s, 50 ms)
# while the estimator rests.
NAP_MARGIN_S = 0.0025
NAP_MIN_S = 0.001
NAP_MAX_S = 0.02
# An impact's onset must not wait for a batch (issue 53 item 2). While the accelerometer's trigger is
# armed, the acquisition naps at most TRIGGER_READ_S, and the ring ends the estimator's wait at once
# for a pushed sample ALARM_K times the trigger's threshold from the stream's level
# (SampleRing.alarm_m_s2): the trigger runs on what has come, and a candidate waiting for its decision
# (a reversal, the arm's states) takes batches of PENDING_BATCH_S (a board's packet). The onset event
# leaves as soon as it is decided, before the episode's first estimates are made (ContactPipeline.on_onset).
TRIGGER_READ_S = 0.0025
ALARM_K = 0.5
PENDING_BATCH_S = 0.0012


def acquisition_loop(source: ImuSource, ring: SampleRing, stop: threading.Event, outbox: Outbox,
                     time_offset_s: float = 0.0) -> None:
    """Transport only: move timestamped SI samples from the source into the ring, and hand the
    source's events (port lost, port back) to the outbox. Between the consumer's batches it naps
    (NAP_MARGIN_S). `time_offset_s` (imu.time_offset_s, calibrated) comes off every stamp: the
    estimator and the recordings see the IMU on the arm's states' clock."""
    while not stop.is_set():
        chunk = source.read(timeout=0.05)
        if chunk is not None:
            if time_offset_s:
                chunk = (chunk[0] - time_offset_s, *chunk[1:])
            ring.push(*chunk)
        for ev in source.drain_events():
            outbox.put("event", {"t": time.monotonic(), **ev})
        ring.hurry.clear()
        nap = ring.shortfall() / source.odr_hz - NAP_MARGIN_S
        if nap >= NAP_MIN_S:
            ring.hurry.wait(min(nap, NAP_MAX_S if ring.alarm_m_s2 == math.inf else TRIGGER_READ_S))


PROPRIO_WAIT_S = 0.05        # the proprioception thread checks its stop event at least this often
PROPRIO_RING = 1024          # proprioception samples waiting for the estimator (about 2 s at 500 Hz)
COMMAND_RING = 256           # control ticks waiting for the estimator (5 s at 50 Hz)


class ProprioFeed:
    """Transport: a robot state to the estimator's ring as TCP pose and twist, at the robot's rate
    (not the 20 ms control tick's). Called for every state a backend admits on the backend's own
    reader thread (RobotBackend.feed_states: a link's reader, which woke for the state anyway), or by
    proprio_loop for a backend without one. `model` is the feed's own ArmModel (its own pinocchio
    Data); a lock keeps two readers apart (an old link's and a fresh one's, for a moment at a
    reconnect). A full ring overwrites the oldest sample (counted and logged): the estimator only
    ever needs the newest ones."""

    def __init__(self, model, ring: DropOldestRing):
        self.model, self.ring = model, ring
        self.seq = -1                     # the newest state's seq taken
        self._logged = 0
        self.gripper = None               # runtime.gripper_worker.GripperWorker once started: its force and opening
        self._lock = threading.Lock()

    def __call__(self, js) -> None:
        with self._lock:
            if js.seq == self.seq:
                return
            self.seq = js.seq
            try:
                oMtcp, twist = self.model.measured(js)
            except Exception:             # a malformed state: skipped, never the end of the reader
                log.exception("proprioception: joint state %d skipped", js.seq)
                return
            grip = np.nan if js.grip_force is None else float(js.grip_force)
            width = grasped = np.nan
            st = None if self.gripper is None else self.gripper.state()
            if st is not None:            # the gripper's own force, where it has one, over the backend's
                grip = grip if st.force_n is None else float(st.force_n)
                width = np.nan if st.width_m is None else float(st.width_m)
                grasped = np.nan if st.grasped is None else float(st.grasped)
            # the joints ride along for the recorder (the Foxglove export draws the arm); the pipeline takes the rest
            ring = self.ring
            ring.push(ProprioSample(js.t, oMtcp.translation.copy(), twist[:3].copy(), oMtcp.rotation.copy(),
                                    twist[3:].copy(), grip, np.array(js.q, dtype=float), width, grasped,
                                    wrench_of(js), js.wrench_source, np.array(js.qd, dtype=float)))
            if ring.overwritten != self._logged and (self._logged == 0 or ring.overwritten - self._logged >= 1000):
                self._logged = ring.overwritten
                log.warning("the estimator fell behind: %d proprioception samples overwritten", self._logged)


def wrench_of(js) -> np.ndarray | None:
    """The arm's own wrench at the TCP as one (6,) array: force N, torque N m, world; nan for a torque it does not
    give; None when it estimates no force."""
    if js.tcp_force is None:
        return None
    out = np.full(6, np.nan)
    out[:3] = js.tcp_force
    if js.tcp_torque is not None:
        out[3:] = js.tcp_torque
    return out


def proprio_loop(robot, feed: ProprioFeed, stop: threading.Event) -> None:
    """The proprioception thread, for a backend whose states no reader of its own hands on: the
    newest state to `feed` each time it changes."""
    while not stop.is_set():
        try:
            js = robot.wait_state(feed.seq, PROPRIO_WAIT_S)
        except Exception as exc:          # the backend has gone: the control thread's faults say so
            log.debug("proprioception: %s", exc)
            stop.wait(PROPRIO_WAIT_S)
            continue
        feed(js)


class EstimatorThread:
    """Owns the contact pipeline. Proprioception arrives on its own ring (`proprio`), the control
    thread's wishes as one `EstimatorDirective` (`directive`); estimates leave through the `contact`
    latest-value slot and the outbox."""

    def __init__(self, pipeline: ContactPipeline, ring: SampleRing, contact, outbox: Outbox,
                 source: ImuSource | None = None, min_batch: int = 1, taps: tuple = (), rests: bool = True,
                 rest_factor: int = REST_BATCH_FACTOR, commands: bool = False):
        """`source` is read for its clipping points (gyro rad/s, accel m/s^2), which change with the
        full scales a board reports, and its data rate, which a board reports in its status packets
        (the onset detector's band window and `min_batch`, one output period of samples, follow it);
        its samples come through the ring. `commands`: the daemon drives the arm, and each control
        tick's command reaches the pipeline (note_command; control.command_track)."""
        self.pipeline = pipeline
        self.taps = tuple(taps)         # each gets every pass (`feed(Pass)`, never blocking): recorder, live view
        self.source = source
        self._odr_seen: float | None = None
        self.output_period_s = pipeline.params.output_period_s
        self.saturated_since: float | None = None   # latest value: the IMU stream has been clipped since then
        self.ring = ring
        # Samples to wait for (up to POP_TIMEOUT_S) before a batch. The pipeline's fixed cost is per
        # batch (some fifty numpy calls), and a source delivers a few samples at a time (8-sample
        # packets from the board): the daemon waits for one output period's worth, which delays
        # an estimate by at most that much.
        self.min_batch = min_batch
        self.contact = contact
        self.outbox = outbox
        self.proprio = DropOldestRing(PROPRIO_RING)
        self.commands = DropOldestRing(COMMAND_RING) if commands else None
        self.directive = LatestValue(EstimatorDirective())
        self.warm = threading.Event()   # set once the pipeline can detect a contact (its onset warm-up is done)
        self.resting = threading.Event()  # set while no task runs: longer batches (REST_BATCH_FACTOR)
        self.rests = rests                # False: never at rest (an observed arm, whose touches are the point)
        self.rest_factor = rest_factor    # a rest batch, in output periods
        # the configured mount and clock, watched over free motion (issue 48 §5)
        self.mount = MountMonitor(pipeline.cond.R_tcp_imu)
        self._mount_checked_t = -math.inf
        self._sent = 0                    # of this pass's events, those already in the outbox (_hand_on)
        pipeline.on_onset = self._hand_on  # an onset leaves as soon as it is decided, within its pass
        if source is not None:
            self._follow_odr(source.odr_hz)

    def _watch_mount(self, batch: np.ndarray, states: list, free: bool) -> None:
        """The running fit of the gyro against the arm's rate over free motion (no contact episode
        before or after this batch: control.mount_fit.MountMonitor), checked about once a second;
        `imu_mount` once if the configured mount or clock is off."""
        if not free:
            self.mount.pause()
            return
        for s in states:
            self.mount.add_state(s.t, s.R_world_tcp)
        if len(batch) == 0:
            return
        self.mount.add_imu(batch[:, 0], batch[:, 1:4])
        t_last = float(batch[-1, 0])
        if t_last - self._mount_checked_t >= 1.0:
            self._mount_checked_t = t_last
            problem = self.mount.check()
            if problem is not None:
                log.warning("%s", problem)
                self.outbox.event("warning", code="imu_mount", message=problem)

    def note_command(self, t: float, qd: np.ndarray) -> None:
        """(the control thread) The tick at t commanded joint rates qd (rad/s; zeros: held)."""
        if self.commands is not None:           # a copy, as the recorder keeps: the tick may reuse its array
            self.commands.push((t, np.array(qd, dtype=float)))

    def set_resting(self, resting: bool) -> None:
        """The control thread: no task runs (True), or one has started (False). A start ends a rest
        batch's wait at the task's batch, so the task's trigger waits no longer than it would have."""
        if resting and self.rests:
            self.resting.set()
        else:
            self.resting.clear()
            self.ring.lower_want(IDLE_BATCH_FACTOR * self.min_batch)

    def _want(self, pipe: ContactPipeline) -> int:
        """The batch to wait for, samples: an output period's while an episode runs; between episodes
        only the trigger runs, and it costs per batch: twice the samples then, rest_factor times while
        no task runs, and a packet's while a candidate waits for its decision."""
        if pipe.tracking:
            return self.min_batch
        if pipe.detector.pending and self._odr_seen:
            return max(1, int(round(PENDING_BATCH_S * self._odr_seen)))
        return (self.rest_factor if self.resting.is_set() else IDLE_BATCH_FACTOR) * self.min_batch

    @staticmethod
    def _alarm(pipe: ContactPipeline) -> float:
        """The ring's alarm (m/s^2; inf: off): ALARM_K times the accelerometer's threshold while it is
        armed between episodes."""
        det = pipe.detector
        if pipe.tracking or not det.armed or det.accel_threshold is None:
            return math.inf
        return ALARM_K * det.accel_threshold_now()

    def _hand_on(self, events: list) -> None:
        """The pass's events not yet handed on go to the outbox (at an onset, from within the pass)."""
        for ev in events[self._sent:]:
            self.outbox.put("event", ev)
        self._sent = len(events)

    def _follow_odr(self, odr_hz: float) -> None:
        if odr_hz == self._odr_seen:
            return
        first = self._odr_seen is None
        self._odr_seen = odr_hz
        problem = self.pipeline.set_odr(odr_hz)
        self.min_batch = max(1, int(odr_hz * self.output_period_s))
        if problem is not None:
            log.warning("%s", problem)
            self.outbox.event("warning", code="imu_rate", message=problem)
        elif not first:
            log.info("IMU data rate now %g Hz: the onset detector's band window follows", odr_hz)

    def run(self, stop: threading.Event) -> None:
        pipe = self.pipeline
        sat_limits = None
        applied = self.directive.get()
        while not stop.is_set():
            directive = self.directive.get()
            if directive is not applied:
                pipe.follow(directive, applied)
                applied = directive
            if self.source is not None:
                self._follow_odr(self.source.odr_hz)
            want = self._want(pipe)
            wait_s = max(POP_TIMEOUT_S, POP_TIMEOUT_MARGIN * want / self._odr_seen) if self._odr_seen else POP_TIMEOUT_S
            batch = self.ring.pop(POP_MAX_SAMPLES, wait_s, want)
            # the arm's states and commands as they stand now, after the wait (an alarm ends a rest
            # batch's wait early: the commands then are what decides an onset at once)
            proprio = self.proprio.drain()
            for sample in proprio:
                pipe.add_sample(sample)
            if self.commands is not None:
                for t_cmd, qd in self.commands.drain():
                    pipe.add_command(t_cmd, qd)
            if self.source is not None:
                limits = self.source.saturation
                if limits != sat_limits:
                    sat_limits = limits
                    pipe.set_saturation(*limits)
            bias = pipe.cond.bias_state() if self.taps else None
            free = not pipe.tracking
            events, est = pipe.process(batch)
            self._watch_mount(batch, proprio, free and not pipe.tracking)
            if self.taps and (len(batch) or proprio):
                done = Pass(proprio, applied, self._odr_seen, sat_limits, batch, events, est, bias)
                for tap in self.taps:
                    tap.feed(done)
            self.saturated_since = pipe.saturated_since
            if not self.warm.is_set() and pipe.warm:
                self.warm.set()
            self.ring.alarm_m_s2 = self._alarm(pipe)
            self._hand_on(events)
            self._sent = 0
            if est is not None:
                self.contact.set(est)
                self.outbox.put("contact", est.to_json())
