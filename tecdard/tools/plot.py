"""`tecdard plot REC.npz -o out.png`: a recording at a glance: the IMU with the onset, the estimate
converging with its 3-sigma band per axis, and its error against the truth where a recording has one.

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


def draw(rec: Recording, rows: np.ndarray, onset_t: float | None, truth: dict, out: str, title: str,
         fmt: str = "png") -> None:
    """Draw to the file `out` in the image format `fmt`. `rows` (k, 7): t, p, std."""
    plt = _pyplot()
    p_true = truth.get("p_c")
    n_panels = 2 + 3 + (1 if p_true is not None and len(rows) else 0)
    fig, axes = plt.subplots(n_panels, 1, figsize=(10, 2.2 * n_panels), sharex=True)
    t0 = rec.imu_t[0]
    t = rec.imu_t - t0
    for ax, data, what in ((axes[0], rec.gyro, "gyro, rad/s (IMU frame)"), (axes[1], rec.accel, "accel, m/s² (IMU frame)")):
        for k in range(3):
            ax.plot(t, data[:, k], lw=0.6, label=AXES[k])
        ax.set_ylabel(what, fontsize=8)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    for ax in axes:
        if onset_t is not None:
            ax.axvline(onset_t - t0, color="k", ls="--", lw=0.8)
    if onset_t is not None:
        axes[0].text(onset_t - t0, axes[0].get_ylim()[1], " onset", va="top", fontsize=8)
    te = rows[:, 0] - t0 if len(rows) else np.zeros(0)
    for k in range(3):
        ax = axes[2 + k]
        if len(rows):
            p, s = rows[:, 1 + k], rows[:, 4 + k]
            ax.plot(te, p, lw=1.0, color=f"C{k}", label=f"estimate {AXES[k]}")
            ax.fill_between(te, p - SIGMA_BAND * s, p + SIGMA_BAND * s, color=f"C{k}", alpha=0.2,
                            label=f"±{SIGMA_BAND:g}σ")
            finite = p[np.isfinite(p)]
            if len(finite):     # the band starts wide: show where the estimate lives
                lo, hi = np.percentile(finite, [2, 98])
                pad = max(0.01, 0.5 * (hi - lo))
                ax.set_ylim(lo - pad, hi + pad)
        if p_true is not None:
            ax.axhline(float(np.asarray(p_true)[k]), color="k", lw=0.8, label="truth")
        ax.set_ylabel(f"contact {AXES[k]}, m", fontsize=8)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    if n_panels == 6:
        d = rows[:, 1:4] - np.asarray(p_true, float)
        axis = truth.get("axis")
        line = truth.get("kind") is not None and "point" not in str(truth.get("kind")) and np.shape(axis) == (3,)
        if line:        # a line contact: along the edge is unobservable; the error is in the plane of rotation
            a = np.asarray(axis, float) / np.linalg.norm(axis)
            d = d - np.outer(d @ a, a)
        axes[5].semilogy(te, np.maximum(np.linalg.norm(d, axis=1), 1e-6) * 1e3, lw=1.0)
        axes[5].set_ylabel("error, mm" + (" (in the plane\nof rotation)" if line else " (3D)"), fontsize=8)
    axes[-1].set_xlabel(f"time since the first sample, s ({title})")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=110, format=fmt)
    except ValueError as exc:
        raise PlotError(f"-o: cannot write {out} ({exc})") from None
    finally:
        plt.close(fig)


def add_parser(sub) -> None:
    p = sub.add_parser("plot", help="draw a recording: IMU and onset, the estimate with its 3-sigma band, its error")
    p.add_argument("recording", help="REC.npz")
    p.add_argument("-o", "--out", required=True, help="image to write (png, pdf, svg)")
    p.add_argument("--method", help="estimator (default: the config's, else ekf)")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline")
    p.add_argument("--ignore-live", action="store_true", help="a daemon recording: replay it as any recording")
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
            draw(rec, rows, onset_t, truth, str(tmp), f"{pathlib.Path(args.recording).name}, {pipeline.method}", fmt)
    except (BadInput, PlotError, RecordingError) as exc:
        return refused("plot", str(exc))
    except OutputError as exc:
        return refused("plot", show_path_error(exc))
    print(f"{args.out}: {len(rows)} estimates ({fmt.upper()})"
          + ("" if onset_t is not None else ", no contact detected"))
    return 0
