"""`tecdard plot REC.npz -o out.png`: a recording at a glance: the IMU with the onset, the TCP's motion
(mm) and the fingertip's turn (deg), the estimate converging in mm with its 3-sigma band per axis (an
axis it cannot observe, along a hinge, is said, not banded), its error against the truth where a
recording has one, and a daemon recording's task start, end and stops marked.

Matplotlib is an extra (`pip install 'tecdar[viz]'`); without it the command says so in one line.
"""
from __future__ import annotations

import pathlib

import numpy as np

from tecdard.recording.format import Recording

SIGMA_BAND = 3.0
AXES = "xyz"


class PlotError(Exception):
    """What keeps a plot from being drawn, in one line."""


def image_format(out: str) -> str:
    """The image format `out` asks for by its suffix (PNG without one: the file is written as named,
    never NAME.png); PlotError for a suffix matplotlib cannot write."""
    plt = _pyplot()
    suffix = pathlib.Path(out).suffix.lower().lstrip(".")
    if not suffix:
        return "png"
    known = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    if suffix not in known:
        raise PlotError(f"-o: no image format for .{suffix[:10]} (known: {', '.join(sorted(known))})")
    return suffix


def _pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise PlotError("needs matplotlib: pip install 'tecdar[viz]'") from None
    return plt


UNOBSERVABLE_M = 0.1     # an axis whose one-sigma ends above this is unobservable (along a hinge): no band
EVENT_KINDS = {"task_started": "start", "contact_onset": "onset", "task_done": "done", "task_failed": "failed",
               "protective_stop": "stop", "fault": "fault"}
BIAS_S = 0.2             # the gyro bias for the angle: the mean over this long before the onset


def turned_deg(rec: Recording, onset_t: float | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The fingertip's rotation since the onset (deg), its gyro integrated less the bias at rest
    before it: (t, angle). None without an onset or rest before it."""
    if onset_t is None:
        return None
    t = rec.imu_t
    pre = (t < onset_t) & (t >= onset_t - BIAS_S)
    if np.count_nonzero(pre) < 10:
        return None
    after = t >= onset_t
    w = rec.gyro[after] - rec.gyro[pre].mean(axis=0)
    dt = np.diff(t[after], prepend=t[after][0])
    return t[after], np.degrees(np.linalg.norm(np.cumsum(w * dt[:, None], axis=0), axis=1))


def _legend(ax) -> None:
    """A legend where the panel has labelled lines (matplotlib warns on an empty one)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", fontsize=7, ncol=3, framealpha=0.6)


def _estimate_panel(ax, k: int, te: np.ndarray, rows: np.ndarray, p_true) -> None:
    """Axis k of the estimate (mm) with its 3-sigma band, or the word that it is unobservable."""
    label = f"contact {AXES[k]}, mm"
    if len(rows):
        p, sd = rows[:, 1 + k] * 1e3, rows[:, 4 + k] * 1e3
        ax.plot(te, p, lw=1.0, color=f"C{k}", label=f"estimate {AXES[k]}")
        unobservable = np.isfinite(sd[-1]) and sd[-1] > UNOBSERVABLE_M * 1e3
        if unobservable:      # along a hinge: the band would hide everything else
            label += f"\nunobservable\n(one-sigma {sd[-1]:.0f} mm)"
        else:
            ax.fill_between(te, p - SIGMA_BAND * sd, p + SIGMA_BAND * sd, color=f"C{k}", alpha=0.2,
                            label=f"±{SIGMA_BAND:g}σ")
        finite = p[np.isfinite(p)]
        if len(finite):     # the band starts wide: show where the estimate lives
            lo, hi = np.percentile(finite, [2, 98])
            pad = max(10.0, 0.5 * (hi - lo))
            ax.set_ylim(lo - pad, hi + pad)
    if p_true is not None:
        ax.axhline(float(np.asarray(p_true)[k]) * 1e3, color="k", lw=0.8, label="truth")
    ax.set_ylabel(label, fontsize=8)
    _legend(ax)


def _error_panel(ax, te: np.ndarray, rows: np.ndarray, truth: dict) -> None:
    d = rows[:, 1:4] - np.asarray(truth["p_c"], float)
    axis = truth.get("axis")
    line = truth.get("kind") is not None and "point" not in str(truth.get("kind")) and np.shape(axis) == (3,)
    if line:        # a line contact: along the edge is unobservable; the error is in the plane of rotation
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        d = d - np.outer(d @ a, a)
    ax.semilogy(te, np.maximum(np.linalg.norm(d, axis=1), 1e-6) * 1e3, lw=1.0)
    ax.set_ylabel("error, mm" + ("\n(in the plane\nof rotation)" if line else " (3D)"), fontsize=8)


def _merged(marks: list, span_s: float, apart: float = 0.015) -> list:
    """The marks' labels, those closer than `apart` of the time span joined ("start, onset"): drawn
    apart they print over each other."""
    out: list = []
    for when, name in sorted(marks):
        if out and when - out[-1][0] < apart * span_s:
            out[-1] = (out[-1][0], f"{out[-1][1]}, {name}")
        else:
            out.append((when, name))
    return out


def draw(rec: Recording, rows: np.ndarray, onset_t: float | None, truth: dict, out: str, title: str,
         fmt: str = "png", events: list | None = None, wrench: np.ndarray | None = None) -> None:
    """Draw to the file `out` in the image format `fmt`. `rows` (k, 7): t, p, std (m); drawn in mm.
    `events`: a daemon recording's (task start and end, stops), marked on every panel. `wrench` (M, 6): a
    daemon recording's `tcp_wrench`, the arm's own force at the TCP drawn under the TCP, against the onset. A
    panel with nothing to show is left out (the turn without an onset, the estimate without one or a truth,
    the force where the arm gives none): the title says no contact was detected."""
    plt = _pyplot()
    p_true = truth.get("p_c")
    turned = turned_deg(rec, onset_t)
    has_est = len(rows) > 0 or p_true is not None
    has_err = p_true is not None and len(rows) > 0
    has_force = wrench is not None and bool(np.any(np.isfinite(wrench[:, :3])))
    n_panels = 3 + has_force + (turned is not None) + 3 * has_est + has_err
    fig, axes = plt.subplots(n_panels, 1, figsize=(10, 1.9 * max(n_panels, 4)), sharex=True,
                             constrained_layout=True)
    panels = iter(axes)
    t0 = rec.imu_t[0]
    t = rec.imu_t - t0
    for data, what in ((rec.gyro, "gyro, rad/s\n(IMU frame)"), (rec.accel, "accel, m/s²\n(IMU frame)")):
        ax = next(panels)
        for k in range(3):
            ax.plot(t, data[:, k], lw=0.6, label=AXES[k])
        ax.set_ylabel(what, fontsize=8)
        _legend(ax)
    ax = next(panels)
    tcp = (rec.tcp_pos - rec.tcp_pos[0]) * 1e3
    for k in range(3):
        ax.plot(rec.tcp_t - t0, tcp[:, k], lw=1.0, label=AXES[k])
    ax.set_ylabel("TCP from its start,\nmm (world)", fontsize=8)
    _legend(ax)
    if has_force:
        ax = next(panels)
        for k in range(3):
            ax.plot(rec.tcp_t - t0, wrench[:, k], lw=0.8, label=AXES[k])
        ax.plot(rec.tcp_t - t0, np.linalg.norm(wrench[:, :3], axis=1), lw=1.0, color="k", label="|F|")
        ax.set_ylabel("the arm's force\nat the TCP, N (world)", fontsize=8)
        _legend(ax)
    if turned is not None:
        ax = next(panels)
        ax.plot(turned[0] - t0, turned[1], lw=1.0, color="C4")
        ax.set_ylabel("fingertip turned\nsince the onset, deg", fontsize=8)
    te = rows[:, 0] - t0 if len(rows) else np.zeros(0)
    if has_est:
        for k in range(3):
            _estimate_panel(next(panels), k, te, rows, p_true)
    if has_err:
        _error_panel(next(panels), te, rows, truth)
    marks = [(onset_t, "onset")] if onset_t is not None else []
    for ev in events or []:
        name = EVENT_KINDS.get(ev.get("kind"))
        if name and isinstance(ev.get("t"), (int, float)) and name != "onset":
            marks.append((float(ev["t"]), name))
    for when, name in marks:
        for ax in axes:
            ax.axvline(when - t0, color="k" if name == "onset" else "0.5", ls="--", lw=0.8)
    for when, name in _merged(marks, span_s=float(t[-1]) if len(t) else 1.0):
        axes[0].annotate(name, (when - t0, 1.0), xycoords=("data", "axes fraction"), fontsize=7,
                         rotation=90, va="top", ha="right")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time since the recording's first sample, s")
    fig.suptitle(title + ("" if onset_t is not None else ": no contact detected"), fontsize=9)
    try:
        fig.savefig(out, dpi=100, format=fmt)
    except ValueError as exc:
        raise PlotError(f"-o: cannot write {out} ({exc})") from None
    finally:
        plt.close(fig)


def add_parser(sub) -> None:
    from tecdard.tools.args import add_replay_options
    p = sub.add_parser("plot", help="draw a recording: IMU and onset, the estimate with its 3-sigma band, its error")
    add_replay_options(p)
    p.add_argument("-o", "--out", required=True, help="image to write (png, pdf, svg)")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard plot`: exit 0, or 2 with one line."""
    from tecdard.files import OutputError, check_output, replacing
    from tecdard.recording.format import RecordingError, load_truth
    from tecdard.tools.args import BadInput, estimates, recording_and_pipeline, refused, show_path_error

    try:
        check_output(args.out, "-o", [args.recording])          # never over the input, and before the replay
        fmt = image_format(args.out)
        rec, live, pipeline = recording_and_pipeline(args)
        rows, onset_t, _ = estimates(args, rec, live, pipeline)
        truth = load_truth(args.recording)
        p_c = truth.get("p_c")
        if np.shape(p_c) != (3,) or np.asarray(p_c).dtype.kind not in "fiu" or not np.all(np.isfinite(p_c)):
            truth.pop("p_c", None)
        with replacing(args.out, "-o") as tmp:                  # a failed write leaves what was there
            draw(rec, rows, onset_t, truth, str(tmp), f"{pathlib.Path(args.recording).name}, {pipeline.method}", fmt,
                 events=None if live is None else live.events, wrench=None if live is None else live.wrench)
    except (BadInput, PlotError, RecordingError) as exc:
        return refused("plot", str(exc))
    except OutputError as exc:
        return refused("plot", show_path_error(exc))
    print(f"{args.out}: {len(rows)} estimates ({fmt.upper()})"
          + ("" if onset_t is not None else ", no contact detected"))
    return 0
