"""Feeding a contact pipeline from a recording: causally in chunks as any recording is replayed, or as
the daemon's live estimator was fed (a daemon recording with its live log). The library under
`tecdard localize`, `plot`, `export`, `calibrate-eta` and the fleet's episode index: each of them replays
through here, so a change of the replay changes all of them alike."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tecdard.config import Config, ConfigError
from tecdard.control.geometry import quat_to_matrix
from tecdard.recording.format import Recording, RecordingError, load_recording
from tecdard.recording.live import LiveLog, load_live
from tecdard.safejson import show

if TYPE_CHECKING:        # the pipeline (and its compiled kernels) loads when a replay runs, not for --help
    from tecdard.control.pipeline import ContactEstimate, ContactPipeline

DIRECTIVE_FIELDS = ("episode", "armed", "arc_following", "bias_held", "begin_t", "since_t")


def replay(rec: Recording, pipeline: ContactPipeline, rate_hz: float = 1000.0, chunk_s: float = 0.1,
           on_estimate=None, on_event=None, commands: np.ndarray | None = None):
    """Run the pipeline over the recording; returns (rows (k, 7): t, p, std; onset_t or None; last estimate).
    `on_estimate(est)` and `on_event(ev)` see each estimate and pipeline event as it comes; `commands`: the
    control ticks' (live_cmd's rows), where the daemon drove the arm.

    Rows come at the estimator's output cadence, never more than rate_hz per second. The
    recording is fed in chunks of chunk_s with the proprioception stamped up to each chunk's
    end; every estimate still uses only samples (and proprioception) stamped at or before it.
    """
    pipeline.params.output_period_s = max(1.0 / rate_hz, pipeline.params.output_period_s)
    t, p, std = [], [], []
    last: ContactEstimate | None = None
    onset_t = None
    for batch in fed_chunks(rec, pipeline, chunk_s, commands):
        events, estimates = pipeline.process_all(batch)
        for ev in events:
            if ev["kind"] == "contact_onset" and onset_t is None:
                onset_t = ev["t"]
            if on_event is not None:
                on_event(ev)
        for est in estimates:
            last = est
            if on_estimate is not None:
                on_estimate(est)
            t.append(est.t)
            p.append(est.p)
            std.append(est.std)
    # the rows stacked once (one concatenate per estimate was a tenth of a replay's time)
    return (np.column_stack([t, p, std]) if t else np.zeros((0, 7))), onset_t, last


def fed_chunks(rec: Recording, pipeline: ContactPipeline, chunk_s: float, commands: np.ndarray | None = None):
    """The recording's IMU samples as (n, 7) batches of chunk_s, each yielded once the pipeline has
    been handed the proprioception stamped up to its end (the TCP's own rate is derived from the
    orientations by the pipeline: recordings carry none), and the control ticks' commands
    (`commands`, live_cmd's (T, 1 + n) rows) up to it."""
    R = quat_to_matrix(rec.tcp_quat)
    vel, force = rec.tcp_vel, rec.grip_force
    batch = np.column_stack([rec.imu_t, rec.gyro, rec.accel])
    grid = np.arange(rec.imu_t[0] + chunk_s, rec.imu_t[-1] + chunk_s, chunk_s)
    ends = np.unique(np.append(np.searchsorted(rec.imu_t, grid, side="right"), len(rec.imu_t)))
    j, start, i = 0, 0, 0  # the next proprioception sample to hand over; the next IMU sample; command
    for end in ends:
        if end <= start:
            continue
        t_end = rec.imu_t[end - 1]
        while j < len(rec.tcp_t) and rec.tcp_t[j] <= t_end:
            pipeline.add_proprio(rec.tcp_t[j], rec.tcp_pos[j], None if vel is None else vel[j], R[j], None,
                                 np.nan if force is None else force[j])
            j += 1
        i = hand_commands(pipeline, commands, i, t_end)
        yield batch[start:end]
        start = end


def hand_commands(pipeline: ContactPipeline, commands: np.ndarray | None, i: int, t_end: float) -> int:
    """The commands (live_cmd rows) from row i stamped up to t_end, to the pipeline: the next row."""
    while commands is not None and i < len(commands) and commands[i, 0] <= t_end:
        pipeline.add_command(commands[i, 0], commands[i, 1:])
        i += 1
    return i


def replay_onsets(rec: Recording, pipeline: ContactPipeline, episode_s: float = 0.3, chunk_s: float = 0.02,
                  commands: np.ndarray | None = None) -> list:
    """Every contact_onset event of a causal replay, each episode released `episode_s` after its
    detection (as a task's end releases it; the trigger then settles and re-arms as the daemon's
    does): how often the trigger fires over a whole recording, not only its first onset."""
    found, release_at = [], None
    for batch in fed_chunks(rec, pipeline, chunk_s, commands):
        if release_at is not None and batch[-1, 0] >= release_at:
            pipeline.release()
            release_at = None
        events, _ = pipeline.process_all(batch)
        for ev in events:
            if ev["kind"] == "contact_onset":
                found.append(ev)
                release_at = ev["detected_t"] + episode_s
    return found


def replay_live(rec: Recording, live: LiveLog, pipeline: ContactPipeline, on_estimate=None):
    """Run the pipeline over a daemon recording as the live estimator ran: the same passes (each
    pass's IMU batch), each proprioception sample added before the pass it reached live, each control
    tick's command (live_cmd) once the pass's samples reach its time, the
    directives, data rates and clipping points as they changed, from the gyro bias the live
    pipeline had at the start. Returns (rows (k, 7): t, p, std, one per estimate the live pass
    published; onset_t or None; last estimate). `pipeline` must be built from the daemon's
    estimator config: then its answer is the live one (docs/recordings.md states the tolerance)."""
    from tecdard.control.pipeline import EstimatorDirective
    R = quat_to_matrix(rec.tcp_quat)
    force = rec.grip_force
    batch = np.column_stack([rec.imu_t, rec.gyro, rec.accel])
    pipeline.cond.set_bias_state(live.bias0)
    changes = {c["pass"]: c for c in live.changes}
    applied = None
    rows, last, onset_t = [], None, None
    j, start, i = 0, 0, 0
    for k, end in enumerate(live.pass_end):
        while j < len(rec.tcp_t) and live.tcp_pass[j] <= k:
            pipeline.add_proprio(rec.tcp_t[j], rec.tcp_pos[j], None if rec.tcp_vel is None else rec.tcp_vel[j], R[j],
                                 live.tcp_w[j], np.nan if force is None else force[j])
            j += 1
        if end > 0:              # the ticks up to the pass's newest sample had reached the estimator live
            i = hand_commands(pipeline, live.cmd, i, rec.imu_t[end - 1])
        change = changes.get(k)
        if change is not None:
            directive = EstimatorDirective(**{f: change["directive"][f] for f in DIRECTIVE_FIELDS
                                              if f in change["directive"]})
            if applied is None:          # the state the live pipeline was in: settings, not a release
                pipeline.set_trigger_armed(directive.armed)
                pipeline.set_arc_following(directive.arc_following)
                pipeline.hold_bias(directive.bias_held)
            else:
                pipeline.follow(directive, applied)
            applied = directive
            if change.get("odr_hz"):
                pipeline.set_odr(float(change["odr_hz"]))
            if change.get("saturation"):
                pipeline.set_saturation(*map(float, change["saturation"]))
        events, est = pipeline.process(batch[start:end])
        start = end
        for ev in events:
            if ev["kind"] == "contact_onset" and onset_t is None:
                onset_t = ev["t"]
        if est is not None:
            last = est
            rows.append(np.concatenate([[est.t], est.p, est.std]))
            if on_estimate is not None:
                on_estimate(est)
    return (np.array(rows) if rows else np.zeros((0, 7))), onset_t, last


class ReplayError(Exception):
    """A recording or config that cannot be replayed, in one line."""


@dataclass
class Replay:
    """A recording, its live log (None: not a daemon's, or replayed as any recording) and the pipeline
    that replays it."""
    rec: Recording
    live: LiveLog | None
    pipeline: ContactPipeline
    name: str                     # the recording's path, as errors name it


def open_replay(path, config: str | None = None, method: str | None = None, ignore_live: bool = False,
                no_plane: bool = False) -> Replay:
    """The recording at `path`, its live_* log (unless ignore_live) and a contact pipeline from the
    `estimator` section of the YAML file `config` (none: the defaults); ReplayError otherwise.
    `method` must be one of control.estimators.names() (the caller checks it and says how)."""
    from tecdard.control.pipeline import ContactPipeline
    try:
        rec = load_recording(path)
        live = None if ignore_live else load_live(path, rec)
    except RecordingError as exc:
        raise ReplayError(str(exc)) from None
    try:
        cfg = Config.load(config) if config else Config({})
        section = cfg.section("estimator")
        pipeline = ContactPipeline.from_config(section, quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
                                               method=method, plane_normal=None if no_plane else rec.plane_normal)
        if no_plane:
            pipeline.params.plane_normal = None
        if pipeline.rate_notice:
            logging.getLogger("tecdar").warning("%s: %s", show(str(path), 200), pipeline.rate_notice)
        unused = section.unused_keys()
        if unused:
            raise ConfigError(f"{unused[0]}: unknown option")
    except ConfigError as exc:
        raise ReplayError(f"config error: {exc}") from None
    return Replay(rec, live, pipeline, str(path))


def run_replay(r: Replay, rate_hz: float = 1000.0, on_estimate=None, on_event=None):
    """(rows (k, 7): t, p, std; onset_t; last estimate) of the replay: as fed live for a daemon
    recording, else causally in chunks; ReplayError (one line) where the estimator cannot take it."""
    try:
        if r.live is not None:
            return replay_live(r.rec, r.live, r.pipeline, on_estimate)
        return replay(r.rec, r.pipeline, rate_hz, on_estimate=on_estimate, on_event=on_event)
    except Exception as exc:        # a recording the checks let through but the estimator cannot take
        logging.getLogger("tecdar").debug("replay failed", exc_info=True)
        first = str(exc).splitlines()[0][:200] if str(exc) else ""
        raise ReplayError(f"{show(r.name, 200)}: could not be replayed ({type(exc).__name__}: {first}); please "
                          "report it with the file") from None
