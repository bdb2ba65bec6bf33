"""`make bench`: the paper's tactile mapping (Experiment C) by the whole daemon on the simulated container; writes benchmarks/mapping.md."""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import sys
import tempfile
import time

import numpy as np
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.control.mapping import kernel_depth, raster_xy  # noqa: E402
from tecdard.sim.world import CONTAINER_M, mapping_scene  # noqa: E402
from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.tools.demo import free_port, start_daemon, stop_daemon  # noqa: E402

HOME_TCP = np.array([0.307, 0.0, 0.52])      # start pose: tool down, above the container
TOOL_LENGTH_M = 0.12            # the paper's eraser, 11 cm, held 30 deg off the vertical
TOOL_TILT_DEG = 30.0
WALL_CLEARANCE_M = 0.01         # the tool tip clears the container walls by this much at the start height
SCENE_ORIGIN_XY = (0.27, -0.175)  # a Panda reaches the whole container from here in both passes
NEAR_M = 0.003                  # per-point error: the nearest true surface within this, horizontally
INSET_M = 0.01                  # the map region stays this far inside the walls
TASK_TIMEOUT_S = 3600.0


def draw_truth(path: pathlib.Path, truth: np.ndarray, out: dict) -> None:
    """The true height field over the map's region, axes in mm and a labelled colour bar, on the
    daemon's depth map's colour scale (its summary's z_min..z_max)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    summary = out["result"]["summary"]
    x0, y0 = (v * 1e3 for v in summary["origin"])
    x1, y1 = x0 + summary["size"][0] * 1e3, y0 + summary["size"][1] * 1e3
    lo, hi = summary["depth"]["z_min"], summary["depth"]["z_max"]
    fig, ax = plt.subplots(figsize=(6.4, 5.0), constrained_layout=True)
    im = ax.imshow(truth * 1e3, origin="lower", extent=(x0, x1, y0, y1), cmap="viridis", interpolation="nearest",
                   vmin=None if lo is None else lo * 1e3, vmax=None if hi is None else hi * 1e3)
    fig.colorbar(im, ax=ax).set_label("surface height, world z, mm")
    ax.set_xlabel("world x, mm")
    ax.set_ylabel("world y, mm")
    ax.set_title("the true height field (the simulated container)", fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def home_q(cfg: dict) -> list[float]:
    """Joint angles putting the TCP at HOME_TCP, tool down, near the configured home posture."""
    import pinocchio as pin
    from tecdard.robots.model import ArmModel
    model = ArmModel(cfg["robot"]["model"])
    q0 = np.array(cfg["robot"]["q_home"], dtype=float)
    oMtcp = model.fk(q0)
    q, ok, err = model.solve_ik(pin.SE3(oMtcp.rotation, HOME_TCP), q0)
    if not ok:
        raise RuntimeError(f"start pose {HOME_TCP.tolist()} unreachable ({err * 1e3:.1f} mm)")
    return [float(x) for x in q]


def run(grid, orientations: int, speed: float, seed: int, out_dir: pathlib.Path) -> dict:
    tilt = np.radians(TOOL_TILT_DEG)
    tip_tcp = [float(TOOL_LENGTH_M * np.sin(tilt)), 0.0, float(TOOL_LENGTH_M * np.cos(tilt))]
    tip_z_home = HOME_TCP[2] - tip_tcp[2]
    floor_z = tip_z_home - WALL_CLEARANCE_M - CONTAINER_M[2]
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["sim"].pop("hinge")
    cfg["sim"]["seed"] = seed
    cfg["sim"]["pivot"] = {"tip_in_tcp": tip_tcp, "surface": "scene", "scene_origin_xy": list(SCENE_ORIGIN_XY),
                           "scene_floor_z": float(floor_z), "scene_seed": seed}
    # a brisker stop after the touch than the default 0.5 m/s^2, so that 2 cm/s descents stay under 5 N
    cfg["control"]["max_accel"] = 2.0
    cfg["control"]["max_jerk"] = 40.0
    # A loaded shared machine can hold up the simulation process or the daemon for 50 ms now and
    # then (one such stall stopped a run at point 26): over a 22 min run the bench measures the
    # map, so it tolerates 0.25 s. The 50 ms stop itself is tested (tests/test_serial_imu.py, unplugging).
    cfg["control"]["imu_stale_s"] = 0.25
    cfg["map"] = {"output_dir": str(out_dir / "maps"), "tool_tip_tcp": tip_tcp, "turn_deg": -90.0}
    cfg["robot"]["q_home"] = home_q(cfg)
    origin = [SCENE_ORIGIN_XY[0] + INSET_M, SCENE_ORIGIN_XY[1] + INSET_M]
    size = [CONTAINER_M[0] - 2 * INSET_M, CONTAINER_M[1] - 2 * INSET_M]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    path = out_dir / "bench.yaml"
    path.write_text(dump_yaml(cfg))
    with open(out_dir / "log", "w") as log:
        proc = start_daemon(str(path), endpoint, log)
        try:
            with Client(endpoint) as cli:
                cli.wait_alive(60)
                t0 = time.monotonic()
                reply = cli.command("map", {"origin": origin, "size": size, "grid": list(grid),
                                            "depth": float(CONTAINER_M[2] + WALL_CLEARANCE_M + 0.005),
                                            "orientations": orientations, "speed": speed})
                if not reply.get("ok"):
                    raise RuntimeError(f"map refused: {reply}")
                ev = cli.wait_event(("task_done", "task_failed"), reply["task"], TASK_TIMEOUT_S)
                elapsed = time.monotonic() - t0
                ticks = cli.command("status")["state"]["control"]
        finally:
            stop_daemon(proc)
    if ev["kind"] != "task_done":
        tail = (out_dir / "log").read_text().splitlines()[-30:]
        raise RuntimeError(f"map failed: {ev.get('error')} (phase {ev.get('phase')})\n" + "\n".join(tail))
    scene = mapping_scene(SCENE_ORIGIN_XY, floor_z, seed=seed)
    stalls = sum("the arm stops" in line for line in (out_dir / "log").read_text().splitlines())
    return {"result": ev["result"], "elapsed_s": elapsed, "scene": scene, "floor_z": floor_z, "ticks": ticks,
            "watchdog_stops": stalls}


def evaluate(out: dict) -> dict:
    res, scene = out["result"], out["scene"]
    summ = res["summary"]
    depth = np.load(res["files"]["depth.npy"])
    query = raster_xy(np.array(summ["origin"]), np.array(summ["size"]), summ["depth"]["resolution"])
    truth = scene.surface_z_many(query.reshape(-1, 2)).reshape(depth.shape)
    pts = np.genfromtxt(res["files"]["points.csv"], delimiter=",", names=True, dtype=None, encoding=None)
    valid = pts[pts["valid"] == 1]
    xy = np.column_stack([valid["x"], valid["y"]])
    z_true = scene.surface_z_many(xy)
    point_err = valid["z"] - z_true
    # A probe that lands on an edge (a box's, a cup's rim) reads the top; a millimetre across the
    # edge the height field is the floor. The distance to the surface allows NEAR_M across.
    offsets = np.array([[dx, dy] for dx in np.linspace(-NEAR_M, NEAR_M, 7) for dy in np.linspace(-NEAR_M, NEAR_M, 7)])
    near = np.stack([scene.surface_z_many(xy + o) for o in offsets], axis=1)
    surface_err = np.min(np.abs(valid["z"][:, None] - near), axis=1)
    # the same estimator fed the true heights at the same probe points: what sampling alone leaves
    ideal = kernel_depth(xy, z_true, query, summ["kernel"]["k"], summ["kernel"]["sigma"])
    return {
        "points": int(summ["points"]), "valid": int(summ["valid"]), "invalid": summ["invalid"],
        "point_rmse_mm": float(np.sqrt(np.mean(point_err ** 2)) * 1e3),
        "point_max_mm": float(np.max(np.abs(point_err)) * 1e3),
        "point_bias_mm": float(np.mean(point_err) * 1e3),
        "surface_rmse_mm": float(np.sqrt(np.mean(surface_err ** 2)) * 1e3),
        "surface_median_mm": float(np.median(surface_err) * 1e3),
        "surface_max_mm": float(np.max(surface_err) * 1e3),
        "map_rmse_mm": float(np.sqrt(np.nanmean((depth - truth) ** 2)) * 1e3),
        "ideal_map_rmse_mm": float(np.sqrt(np.nanmean((ideal - truth) ** 2)) * 1e3),
        "map_vs_ideal_rmse_mm": float(np.sqrt(np.nanmean((depth - ideal) ** 2)) * 1e3),
        "elapsed_s": out["elapsed_s"], "truth": truth, "depth": depth, "ticks": out["ticks"],
        "watchdog_stops": out["watchdog_stops"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.mapping")
    ap.add_argument("--grid", default="5,6", help="rows,cols (default the paper's 5,6)")
    ap.add_argument("--orientations", type=int, default=2)
    ap.add_argument("--speed", type=float, default=0.02, help="descent and probe speed, m/s")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    grid = [int(x) for x in args.grid.split(",")]
    here = pathlib.Path(__file__).resolve().parent
    with tempfile.TemporaryDirectory() as tmp:
        out = run(grid, args.orientations, args.speed, args.seed, pathlib.Path(tmp))
        m = evaluate(out)
        shutil.copy(out["result"]["files"]["depth.png"], here / "mapping_depth.png")
        shutil.copy(out["result"]["files"]["points.csv"], here / "mapping_points.csv")
        draw_truth(here / "mapping_truth.png", m["truth"], out)
    lines = [
        f"# Tactile mapping ({time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores)", "",
        "`python -m benchmarks.mapping`: the whole daemon maps the simulated container of the paper's",
        f"Experiment C (45 x 35 x 24.5 cm, seed {args.seed}: two books, a box, two cups) with a block held",
        f"{TOOL_TILT_DEG:.0f} deg off the vertical, {TOOL_LENGTH_M * 100:.0f} cm. Grid {grid[0]} x {grid[1]},"
        f" {args.orientations} orientation(s), descent and probe at {args.speed * 1e3:.0f} mm/s"
        " (control.max_accel 2 m/s^2, max_jerk 40 m/s^3, imu_stale_s 0.25 s).", "",
        "| figure | value |", "|---|---|",
        f"| points probed / valid | {m['points']} / {m['valid']} (invalid: {json.dumps(m['invalid'])}) |",
        f"| per-point height error at the estimated x-y: RMSE, max, mean | {m['point_rmse_mm']:.1f} mm,"
        f" {m['point_max_mm']:.1f} mm, {m['point_bias_mm']:+.1f} mm |",
        f"| per-point distance to the true surface within {NEAR_M * 1e3:.0f} mm across: median, RMSE, max |"
        f" {m['surface_median_mm']:.1f} mm, {m['surface_rmse_mm']:.1f} mm, {m['surface_max_mm']:.1f} mm |",
        f"| map RMSE against the true height field | {m['map_rmse_mm']:.1f} mm |",
        f"| the same kernel estimator fed the true heights at the probe points | {m['ideal_map_rmse_mm']:.1f} mm |",
        f"| map against that ideal map | {m['map_vs_ideal_rmse_mm']:.1f} mm |",
        f"| wall time | {m['elapsed_s'] / 60:.1f} min ({m['elapsed_s'] / max(m['points'], 1):.1f} s per point) |",
        f"| control ticks: overruns over the run; lateness p99 / max over the last 1000 | {m['ticks'].get('overruns')},"
        f" {m['ticks'].get('late_ms_p99')} / {m['ticks'].get('late_ms_max')} ms |",
        f"| simulated arm stopped by its command watchdog (control thread stalled > 0.1 s) | {m['watchdog_stops']} |", "",
        "The map's RMSE is mostly sampling: a 7 cm grid cannot resolve 4 mm cup rims or the edges of",
        "books, and the ideal map (true heights at the same points) has nearly the same RMSE. The",
        "per-point error is what the touch itself adds. Probes that land on an edge (a box's, a cup's",
        "4 mm rim) read its top while the height field a millimetre across is the floor: the",
        "first per-point line counts those as errors of the full height, the second does not.",
        "The probes are in [mapping_points.csv](mapping_points.csv).", "",
        "![map](mapping_depth.png) ![truth](mapping_truth.png)", "",
        "Left: depth.png as written by the daemon (black dots: valid probes, red crosses: invalid).",
        "Right: the true height field over the same region, on the same colour scale.", "",
    ]
    (here / "mapping.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
