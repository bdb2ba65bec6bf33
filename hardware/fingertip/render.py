"""`make fingertip`: every part of fingertip.scad as an STL (OpenSCAD), each checked closed, and the assembly
drawn exploded with its axes in mm (docs/img/fingertip.png).

OpenSCAD's own PNG export needs an OpenGL context, which a headless machine does not have; the drawing is
made from the STL files instead, with matplotlib."""
from __future__ import annotations

import argparse
import pathlib
import shutil
import subprocess
import sys
from collections import Counter

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
SCAD = HERE / "fingertip.scad"
PARTS = ("pad", "carrier", "mould", "locator", "backing_franka", "backing_robotiq")
RENDER_TIMEOUT_S = 300.0
# the drawing: each part's colour and its offset along z, mm (the mould below, the backing above the pad)
EXPLODED = {"mould": ("#b0b0b0", -16.0), "pad": ("#f39c12", 0.0), "carrier": ("#1e7b34", 0.0),
            "backing_franka": ("#3a6ea5", 12.0)}


def render(part: str, out_dir: pathlib.Path, scad: pathlib.Path = SCAD, **params) -> pathlib.Path:
    """One part to out_dir/<part>.stl (ASCII); OpenSCAD's error in one line on failure."""
    if shutil.which("openscad") is None:
        raise RuntimeError("openscad is not installed (apt install openscad; .ci/run installs it)")
    out = out_dir / f"{part}.stl"
    defs = [f"-D{k}={v}" for k, v in params.items()]
    proc = subprocess.run(["openscad", "-D", f'part="{part}"', *defs, "-o", str(out), str(scad)],
                          capture_output=True, text=True, timeout=RENDER_TIMEOUT_S)
    problems = [ln for ln in proc.stderr.splitlines() if "ERROR" in ln or "WARNING" in ln]
    if proc.returncode != 0 or problems or not out.exists():
        raise RuntimeError(f"openscad {part}: " + ("; ".join(problems) or f"exit {proc.returncode}"))
    return out


def read_stl(path: pathlib.Path) -> np.ndarray:
    """The triangles of an ASCII STL, (n, 3, 3) in mm."""
    vertices = [line.split()[1:4] for line in path.read_text().splitlines() if line.strip().startswith("vertex")]
    if not vertices or len(vertices) % 3:
        raise ValueError(f"{path.name}: no whole triangles (an ASCII STL expected)")
    return np.asarray(vertices, dtype=float).reshape(-1, 3, 3)


def mesh_problems(triangles: np.ndarray, decimals: int = 5) -> list[str]:
    """Why the mesh is not a closed, consistently oriented surface, or []: every edge must be shared by
    exactly two triangles that run along it in opposite directions, and the enclosed volume must be positive."""
    keys = np.round(triangles, decimals)
    directed: Counter = Counter()
    for tri in keys:
        pts = [tuple(p) for p in tri]
        for a, b in ((0, 1), (1, 2), (2, 0)):
            directed[(pts[a], pts[b])] += 1
    problems = []
    doubled = sum(1 for n in directed.values() if n > 1)
    unmatched = sum(1 for (a, b) in directed if (b, a) not in directed)
    if doubled:
        problems.append(f"{doubled} edges run the same way in two triangles (inconsistent orientation or a seam)")
    if unmatched:
        problems.append(f"{unmatched} edges belong to one triangle only (a hole)")
    volume = float(np.einsum("ij,ij->i", keys[:, 0], np.cross(keys[:, 1], keys[:, 2])).sum() / 6.0)
    if volume <= 0:
        problems.append(f"enclosed volume {volume:.3f} mm^3 is not positive (inside out)")
    return problems


def volume_mm3(triangles: np.ndarray) -> float:
    return float(np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum() / 6.0)


def shaded(triangles: np.ndarray, colour: str, alpha: float) -> np.ndarray:
    """Each face's RGBA under a light from above and in front (matplotlib draws 3D faces flat)."""
    from matplotlib.colors import to_rgb
    n = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([-0.4, -0.6, 0.7]) / np.linalg.norm([-0.4, -0.6, 0.7])
    k = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)
    rgba = np.empty((len(triangles), 4))
    rgba[:, :3] = k[:, None] * np.asarray(to_rgb(colour))
    rgba[:, 3] = alpha
    return rgba


def draw(stls: dict[str, pathlib.Path], png: pathlib.Path) -> None:
    """The assembly exploded along z, axes in mm."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(7.5, 6.0))
    ax = fig.add_subplot(projection="3d")
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for part, (colour, dz) in EXPLODED.items():
        tris = read_stl(stls[part]) + np.array([0.0, 0.0, dz])
        alpha = {"mould": 0.35, "pad": 0.45}.get(part, 1.0)     # see-through: the cavity, and the carrier in the pad
        ax.add_collection3d(Poly3DCollection(tris, facecolors=shaded(tris, colour, alpha), edgecolors="none"))
        lo, hi = np.minimum(lo, tris.reshape(-1, 3).min(0)), np.maximum(hi, tris.reshape(-1, 3).max(0))
    span = (hi - lo).max() / 2
    mid = (hi + lo) / 2
    ax.set(xlim=(mid[0] - span, mid[0] + span), ylim=(mid[1] - span, mid[1] + span), zlim=(mid[2] - span, mid[2] + span),
           xlabel="x along the finger (mm)", ylabel="y across (mm)", zlabel="z from the contact face (mm)")
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=22, azim=-58)
    ax.set_title("tecdar fingertip, exploded: mould, silicone pad with the IMU carrier, backing (Franka mount)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c, _ in EXPLODED.values()]
    ax.legend(handles, ["mould (z -16 mm)", "silicone pad", "IMU carrier, cast in", "backing (z +12 mm)"],
              loc="upper left", fontsize=8)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="render the fingertip's parts (STL) and its drawing (PNG)")
    ap.add_argument("--out", type=pathlib.Path, default=HERE / "build", help="where the STL files go")
    ap.add_argument("--png", type=pathlib.Path, default=HERE.parent.parent / "docs" / "img" / "fingertip.png")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    stls, bad = {}, 0
    for part in PARTS:
        try:
            stls[part] = render(part, args.out)
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            print(f"fingertip: {exc}", file=sys.stderr)
            return 1
        tris = read_stl(stls[part])
        problems = mesh_problems(tris)
        bad += bool(problems)
        print(f"{stls[part].relative_to(HERE.parent.parent) if stls[part].is_relative_to(HERE.parent.parent) else stls[part]}: "
              f"{len(tris)} triangles, {volume_mm3(tris) / 1000:.2f} cm^3, "
              + ("closed" if not problems else "NOT CLOSED: " + "; ".join(problems)))
    draw(stls, args.png)
    print(f"{args.png}: the assembly, exploded")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
