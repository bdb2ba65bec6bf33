"""The map verb's service: fuse a finished map run into a depth raster and write depth.npy, points.csv,
summary.json and depth.png, on a thread of its own."""
from __future__ import annotations

import concurrent.futures
import csv
import json
import logging
import pathlib
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from tecdard.control.mapping import MapRecord, kernel_depth, raster_xy
from tecdard.files import OutputError, atomic_dir, ensure_writable_dir, state_dir
from tecdard.options import option, read_options
from tecdard.verbs import VerbService

log = logging.getLogger("tecdar.map")

PNG_CELL_PX_MAX = 8           # a raster cell is drawn as at most this many pixels square
PNG_TARGET_PX = 480           # the longer side of the heatmap aims at this many pixels
COLORBAR_PX = 24
NAN_RGB = (200, 200, 200)
# viridis, sampled at eight points (matplotlib's, which the core does not depend on)
_VIRIDIS = np.array([[68, 1, 84], [70, 50, 127], [54, 92, 141], [39, 127, 142], [31, 161, 135],
                     [74, 194, 109], [159, 218, 58], [253, 231, 37]], dtype=float)


def default_output_dir() -> str:
    """<state directory>/maps: systemd's StateDirectory when run as the service, else the user's
    state directory (tecdard.files.state_dir), never the working directory."""
    return str(state_dir() / "maps")


@dataclass
class MapSettings:
    """The `map` config section: how a run probes and how its map is fused and written."""
    output_dir: str = option(default_output_dir, "where each map's directory is written (made and checked at "
                                                 "start)", shown="$STATE_DIRECTORY/maps under systemd, else "
                                                                 "~/.local/state/tecdar/maps")
    resolution_m: float = option(0.005, "the raster cell of depth.npy", unit="m", minval=0.001, maxval=0.1)
    kernel_k: int = option(4, "the paper's k nearest probes fused per cell", minval=1, maxval=64)
    kernel_sigma_m: float = option(0.022, "the paper's sigma = 2.2 (no unit given; cm fits its 7-9 cm grid)",
                                   unit="m", above=0.0, maxval=1.0)
    abort_force_n: float = option(5.0, "the paper's 5 N: a point is abandoned above this TCP force", unit="N",
                                  above=0.0, maxval=100.0)
    max_point_std_m: float = option(0.005, "a probe is valid when the in-plane one-sigma is below this", unit="m",
                                    above=0.0, maxval=0.1)
    probe_distance_m: float = option(0.005, "the tangential probe (the paper's at most 5 mm)", unit="m",
                                     minval=0.001, maxval=0.02)
    tool_tip_tcp: tuple = option((0.0, 0.0, 0.1), "the held probe's far end, TCP frame, nominal (refined by each "
                                                  "probe)", unit="m", kind="vec3")
    turn_deg: float = option(90.0, "the second pass turns the tool this much about world z (sign: the arm's reach)",
                             unit="deg", minval=-180.0, maxval=180.0)
    release_distance_m: float = option(0.008, "each lift first pulls the tool out along its axis this far (beyond "
                                              "the grasp's preload)", unit="m", minval=0.0, maxval=0.05)

    @classmethod
    def from_config(cls, section) -> "MapSettings":
        params = read_options(cls, section)
        params.output_dir = _checked_dir(section, params.output_dir)
        return params


def _checked_dir(section, path: str) -> str:
    """map.output_dir, created and proven writable at start-up (not at the end of a map)."""
    try:
        ensure_writable_dir(path, "output_dir")
    except OutputError as exc:
        raise section.error("output_dir", exc.reason) from None
    return path


def fuse(record: MapRecord, settings: MapSettings) -> tuple[np.ndarray, np.ndarray]:
    """(query raster (ny, nx, 2), surface height (ny, nx)) from the valid points of every pass, m."""
    m = record.params
    valid = [pt for pt in record.points if pt.valid]
    xy = np.array([pt.p[:2] for pt in valid]).reshape(-1, 2)
    z = np.array([pt.p[2] for pt in valid])
    query = raster_xy(m.origin_xy, m.size_xy, settings.resolution_m)
    return query, kernel_depth(xy, z, query, settings.kernel_k, settings.kernel_sigma_m)


def write_map(record: MapRecord, settings: MapSettings) -> dict:
    """Fuse and write the four files into <output_dir>/<task id>/ (mode 0700, files 0600); returns
    the task result. The directory appears complete or not at all: the files are written into a
    temporary directory beside it, synced, and renamed in one step (tecdard.files.atomic_dir)."""
    final = pathlib.Path(settings.output_dir) / record.task_id
    ensure_writable_dir(settings.output_dir, "map.output_dir")
    with atomic_dir(final) as tmp:
        summary = _write_files(record, settings, tmp)
    files = {name: str(final / name) for name in ("depth.npy", "points.csv", "summary.json", "depth.png")}
    return {"path": str(final), "files": files, "summary": summary}


def _write_files(record: MapRecord, settings: MapSettings, out: pathlib.Path) -> dict:
    m = record.params
    query, height = fuse(record, settings)
    np.save(out / "depth.npy", height)
    rows = [pt.to_row() for pt in record.points]
    with open(out / "points.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["pass"])
        writer.writeheader()
        writer.writerows(rows)
    valid = [pt for pt in record.points if pt.valid]
    reasons: dict[str, int] = {}
    for pt in record.points:
        if not pt.valid:
            reasons[pt.reason] = reasons.get(pt.reason, 0) + 1
    finite = height[np.isfinite(height)]
    summary = {
        "grid": list(m.grid), "origin": m.origin_xy.tolist(), "size": m.size_xy.tolist(),
        "passes": len(record.yaw_rad), "yaw_deg": [float(np.degrees(y)) for y in record.yaw_rad],
        "points": len(record.points), "valid": len(valid), "invalid": reasons,
        "depth": {"file": "depth.npy", "quantity": "surface height, world z, m",
                  "shape": list(height.shape), "rows": "+y", "cols": "+x",
                  "first_cell_center": query[0, 0].tolist(), "resolution": settings.resolution_m,
                  "z_min": float(finite.min()) if finite.size else None,
                  "z_max": float(finite.max()) if finite.size else None},
        "kernel": {"k": settings.kernel_k, "sigma": settings.kernel_sigma_m},
        "median_std_z": float(np.median([pt.std[2] for pt in valid])) if valid else None,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if not draw_depth(out / "depth.png", height, record, m):       # without matplotlib: the raw raster
        write_png(out / "depth.png", heatmap_rgb(height, query, valid, record.points, m))
    return summary


def draw_depth(path, height: np.ndarray, record, m) -> bool:
    """depth.png as a figure a person reads: world x and y in mm on the axes, the surface height in mm
    on a labelled colour bar, the probes marked (valid, invalid). False where matplotlib (the `viz`
    extra) is not installed. The object-oriented API only (no pyplot): this runs on the map writer's
    thread."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return False
    x0, y0 = (float(v) * 1e3 for v in m.origin_xy)
    x1, y1 = x0 + float(m.size_xy[0]) * 1e3, y0 + float(m.size_xy[1]) * 1e3
    fig = Figure(figsize=(6.4, 5.0), constrained_layout=True)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    im = ax.imshow(height * 1e3, origin="lower", extent=(x0, x1, y0, y1), cmap="viridis", interpolation="nearest")
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("surface height, world z, mm")
    good = np.array([pt.p[:2] for pt in record.points if pt.valid]).reshape(-1, 2) * 1e3
    bad = np.array([pt.grid_xy for pt in record.points if not pt.valid]).reshape(-1, 2) * 1e3
    if len(good):
        ax.plot(good[:, 0], good[:, 1], "k.", ms=5, label=f"probe, valid ({len(good)})")
    if len(bad):
        ax.plot(bad[:, 0], bad[:, 1], "x", color="tab:red", ms=6, label=f"probe, invalid ({len(bad)})")
    if len(good) or len(bad):
        ax.legend(loc="upper right", fontsize=8, framealpha=0.7)
    ax.set_xlabel("world x, mm")
    ax.set_ylabel("world y, mm")
    ax.set_title(f"tactile depth map {record.task_id}: {len(good)} of {len(record.points)} probes valid", fontsize=9)
    fig.savefig(path, dpi=100, format="png")
    return True


def colormap(t: np.ndarray) -> np.ndarray:
    """Viridis RGB (..., 3) uint8 for t in [0, 1]; NaN -> grey."""
    t = np.asarray(t, dtype=float)
    x = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(x.astype(int), len(_VIRIDIS) - 2)
    f = (x - i)[..., None]
    rgb = (1.0 - f) * _VIRIDIS[i] + f * _VIRIDIS[i + 1]
    rgb[np.isnan(t)] = NAN_RGB
    return rgb.astype(np.uint8)


def heatmap_rgb(height: np.ndarray, query: np.ndarray, valid, points, m) -> np.ndarray:
    """The height raster as an image (+y up), probe points marked (valid black, invalid red),
    and a colour bar on the right (bottom: z_min, top: z_max; values in summary.json)."""
    finite = height[np.isfinite(height)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    span = hi - lo if hi > lo else 1.0
    ny, nx = height.shape
    cell = int(max(1, min(PNG_CELL_PX_MAX, PNG_TARGET_PX // max(nx, ny))))
    img = np.repeat(np.repeat(colormap((height - lo) / span), cell, axis=0), cell, axis=1)[::-1]

    def mark(x, y, rgb) -> None:
        j = int((x - m.origin_xy[0]) / m.size_xy[0] * nx * cell)
        i = img.shape[0] - 1 - int((y - m.origin_xy[1]) / m.size_xy[1] * ny * cell)
        img[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3] = rgb

    for pt in points:
        if pt.valid:
            mark(pt.p[0], pt.p[1], (0, 0, 0))
        else:
            mark(pt.grid_xy[0], pt.grid_xy[1], (220, 30, 30))
    bar = colormap(np.linspace(1.0, 0.0, img.shape[0]))[:, None, :].repeat(COLORBAR_PX, axis=1)
    gap = np.full((img.shape[0], 4, 3), 255, dtype=np.uint8)
    return np.concatenate([img, gap, bar], axis=1)


def write_png(path, rgb: np.ndarray) -> None:
    """An 8-bit RGB PNG (h, w, 3) with zlib: no imaging library needed."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), rgb.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    pathlib.Path(path).write_bytes(png)


class MapFiles(VerbService):
    """The map verb's service (tecdard.verbs.VerbService): fuses and writes maps on a thread of its own,
    never on the control tick. A map that ends early (stopped, cancelled, failed) is written all the
    same; `announcements()` gives, once each, the `map_written` or `map_write_failed` event of every
    such map whose write has finished."""

    @classmethod
    def from_config(cls, section) -> "MapFiles":
        """From the `map` section (MapSettings)."""
        return cls(MapSettings.from_config(section))

    def __init__(self, settings: MapSettings):
        self.settings = settings
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-writer")
        self._writes: list[concurrent.futures.Future] = []
        self._partial: list[tuple[str, concurrent.futures.Future]] = []   # (task id, write) of ended maps

    def write(self, record: MapRecord) -> concurrent.futures.Future:
        fut = self._pool.submit(write_map, record, self.settings)
        self._writes = [f for f in self._writes if not f.done()] + [fut]
        return fut

    def write_partial(self, task_id: str, record: MapRecord) -> None:
        self._partial.append((task_id, self.write(record)))

    @property
    def idle(self) -> bool:
        """Every write done, and every early-ended map's `map_written` handed on (an orderly
        shutdown waits for both: a map written after the arm came to rest was once never said)."""
        return all(f.done() for f in self._writes) and not self._partial

    def announcements(self) -> list[dict]:
        """Event fields (kind first) for each early-ended map written since the last call."""
        out = []
        for item in [m for m in self._partial if m[1].done()]:
            self._partial.remove(item)
            task_id, fut = item
            exc = fut.exception()
            if exc is None:
                res = fut.result()
                out.append({"kind": "map_written", "task": task_id, "map_path": res["path"], "files": res["files"],
                            "summary": res["summary"]})
            else:
                log.error("map %s: the points probed were not written: %s", task_id, exc)
                out.append({"kind": "map_write_failed", "task": task_id, "error": f"{type(exc).__name__}: {exc}"})
        return out

    def shutdown(self, wait: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=not wait)
