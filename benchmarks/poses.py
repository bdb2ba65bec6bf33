"""`rotate` over a grid of hinge poses (issue 21): the whole daemon on the simulated cutter; writes
benchmarks/poses.md.

    python -m benchmarks.poses [--quick]

The TCP starts at the home pose of configs/sim.yaml. The cutter's hinge is placed `radius` from it
along the handle's direction, given by its elevation (the handle rising from the hinge to the TCP)
and its yaw (where the hinge lies, seen from above: 0 behind the gripper, along -x); the hinge's
axis is horizontal and square to the handle. Each run probes along the handle's tangent at the
grasp, as Algorithm 2 of the paper does, and turns the handle 30 deg; a row is the hinge error
(the distance from the estimate to the true axis) and the cutter's base displacement.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import platform
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.__main__ import HOME_TCP, bench_rotate  # noqa: E402

ELEVATIONS_DEG = (-20.0, 0.0, 20.0, 40.0)
YAWS_DEG = (0.0, 45.0, -60.0, 90.0)
RADII_M = (0.08, 0.15, 0.25)
HINGE_TARGET_MM = 5.0        # issue 21's target for the hinge
BASE_TARGET_MM = 2.0


def grid_pose(elevation_deg: float, yaw_deg: float, radius: float) -> dict:
    """The hinge `radius` from the home TCP: handle direction from its elevation and yaw, axis
    horizontal and square to it."""
    e, y = np.radians(elevation_deg), np.radians(yaw_deg)
    u = np.array([np.cos(e) * np.cos(y), -np.cos(e) * np.sin(y), np.sin(e)])    # hinge -> TCP
    axis = np.array([np.sin(y), np.cos(y), 0.0])
    return {"point": (HOME_TCP - radius * u).tolist(), "axis": axis.tolist()}


def tangent(pose: dict) -> list[float]:
    """The handle's tangent at the grasp, upwards (the probe direction)."""
    e0 = HOME_TCP - np.array(pose["point"])
    e0 /= np.linalg.norm(e0)
    t = np.cross(np.array(pose["axis"]), e0)
    t = t if t[2] >= 0 else -t
    return [float(x) for x in t]


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.poses")
    ap.add_argument("--quick", action="store_true", help="one radius, two poses")
    args = ap.parse_args()
    t_start = time.time()
    cases = [(e, y, r) for e in ELEVATIONS_DEG for y in YAWS_DEG for r in RADII_M
             if not (e == 0.0 and y == 0.0)]          # the default pose is benchmarks/daemon.md's
    if args.quick:
        cases = [(20.0, 45.0, 0.15), (-20.0, -60.0, 0.15)]
    rows = []
    for e, y, r in cases:
        pose = grid_pose(e, y, r)
        res = bench_rotate(r, 1, "arc", 30.0, pose_spec=pose, direction=tangent(pose))
        res.update(elevation=e, yaw=y)
        rows.append(res)
        print({k: res.get(k) for k in ("elevation", "yaw", "radius", "hinge_err_mm", "base_mm", "failed")},
              flush=True)
    lines = [f"# `rotate` over hinge poses ({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()})", "",
             *[part.replace("\n", " ") + "\n" for part in __doc__.split("\n\n")[2:3]],
             "| handle elevation | hinge yaw | radius | hinge error | base moved | angle error |", "|---|---|---|---|---|---|"]
    for r in rows:
        head = f"| {r['elevation']:+.0f} deg | {r['yaw']:+.0f} deg | {r['radius'] * 100:.0f} cm |"
        if "failed" in r:
            lines.append(f"{head} failed: {r['failed']} | {r['base_mm']:.2f} mm | |")
        else:
            lines.append(f"{head} {r['hinge_err_mm']:.2f} mm | {r['base_mm']:.2f} mm | {r['angle_err_deg']:+.2f} deg |")
    done = [r for r in rows if "failed" not in r]
    lines += [""]
    if done:
        errs = [r["hinge_err_mm"] for r in done]
        lines.append(f"{len(done)} of {len(rows)} runs finished: hinge error median {statistics.median(errs):.2f} mm, "
                     f"max {max(errs):.2f} mm, {sum(e < HINGE_TARGET_MM for e in errs)} within "
                     f"{HINGE_TARGET_MM:g} mm; base moved at most {max(r['base_mm'] for r in done):.2f} mm "
                     f"(target {BASE_TARGET_MM:g} mm).")
    lines += ["", f"Run time {time.time() - t_start:.0f} s."]
    out = ROOT / "benchmarks" / "poses.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"\nwritten {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
