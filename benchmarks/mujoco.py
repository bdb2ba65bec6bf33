"""The estimators on the second source, MuJoCo's rigid-body physics (issue 21); writes benchmarks/mujoco.md.

    python -m benchmarks.mujoco [--seeds N]

Recordings from sim/mujoco_source.py (no signal model shared with sim/scenarios.py): the paper
cutter, arcs with the gripper held or turning with the handle, and straight pushes, at lever arms
of 4, 8 and 12 cm, and a 12 cm arc whose grasp slips on the handle once the fingertip's twist
torque passes 0.05 N m (about 3.5 deg of handle, 0.3-0.45 s in); a pen of 9 or 14 cm on its
tip (a point contact), its top circled at 3 cm/s on a 2 cm circle with the gripper held; and a
block on a table tipped up on its bottom edge against a ridge (MuJoCo's contacts, which give a
little), grasped at its top 8 or 12 cm from the edge, from rest (tilt) or slid into the ridge
at 20 mm/s and tipped on without stopping (ongoing); with encoder-grade TCP noise (0.05 mm at 500 Hz, TCP velocity reported) or the
paper's (0.5 mm at 65 Hz, no velocity). The fingertip's twist lags by 3 ms (the silicone's
damping), and the estimator is told so (`estimator.fingertip_lag_s`, its default).

Each method runs from the true onset, commanded, so that the methods are compared on the same
samples; the trigger's own latency is reported apart. Errors are
in the plane of rotation (along the hinge is unobservable), 3D for the pen, in mm, at 30 ms, 180 ms
and the end, as medians over seeds. Coverage is the share of estimates whose in-plane error lies within 3σ on
every observable axis.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import platform
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.control.geometry import quat_to_matrix  # noqa: E402
from tecdard.sim.mujoco_source import MujocoScenario, generate  # noqa: E402
from tecdard.recording import replay as L  # noqa: E402
from tecdard.config import Config  # noqa: E402
from tecdard.control.pipeline import ContactPipeline  # noqa: E402
from tecdard.recording.format import Recording  # noqa: E402

METHODS = ("ekf", "paper-ekf", "svd-geo", "svd-diff")
HORIZONS_S = (0.03, 0.18)
GRADES = {"encoder": dict(tcp_noise=5e-5, tcp_hz=500.0, with_tcp_vel=True),
          "paper": dict(tcp_noise=5e-4, tcp_hz=65.0, with_tcp_vel=False)}
CASES = [(m, r) for m in ("arc", "arc-turning", "push") for r in (0.04, 0.08, 0.12)] + \
    [("slip", 0.12), ("circle", 0.09), ("circle", 0.14), ("tilt", 0.08), ("tilt", 0.12), ("ongoing", 0.08), ("ongoing", 0.12)]
LAGS_S = (0.0, 0.0015, 0.003, 0.0045, 0.006)


def evaluate(rec: Recording, truth: dict, method: str, **estimator) -> dict:
    pipe = ContactPipeline.from_config(
        Config({"estimator": estimator}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
        method=method)
    pipe.begin(float(truth["onset_t"]))
    rows, _, _ = L.replay(rec, pipe)
    a = truth["axis"]
    d = rows[:, 1:4] - truth["p_c"]
    d_plane = d - np.outer(d @ a, a)
    err = np.linalg.norm(d_plane, axis=1)
    since = rows[:, 0] - float(truth["onset_t"])
    std = rows[:, 4:7]
    observable = std < 0.1
    covered = np.all((np.abs(d_plane) <= 3 * std) | ~observable, axis=1)
    at = [float(err[min(np.searchsorted(since, h), len(err) - 1)]) for h in HORIZONS_S]
    return {"e": at + [float(err[-1])], "coverage": float(covered.mean())}


def latency(rec: Recording, truth: dict) -> float | None:
    pipe = ContactPipeline.from_config(
        Config({}).section("estimator"), quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz)
    _, onset_t, _ = L.replay(rec, pipe)
    return None if onset_t is None else onset_t - float(truth["onset_t"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    t0 = time.time()
    table = {}          # (grade, motion, radius) -> method -> [results]
    lat = []
    for grade, noise in GRADES.items():
        for motion, radius in CASES:
            for seed in range(1, args.seeds + 1):
                speed = 0.03 if motion == "circle" else 0.02
                fields, truth = generate(MujocoScenario(motion=motion, radius=radius, speed=speed, seed=seed, **noise))
                rec = Recording.from_fields(fields)
                for m in METHODS:
                    table.setdefault((grade, motion, radius), {}).setdefault(m, []).append(evaluate(rec, truth, m))
                if grade == "encoder":
                    lat.append(latency(rec, truth))
    lines = [f"# Estimation on MuJoCo recordings ({time.strftime('%Y-%m-%d')}, {platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()})", "",
             *[part.replace("\n", " ") + "\n" for part in __doc__.split("\n\n")[2:4]],
             f"{args.seeds} seeds per case.", ""]
    for grade in GRADES:
        lines += [f"## {grade}-grade TCP noise", "",
                  "| case | " + " | ".join(f"{m} 30 ms / 180 ms / end" for m in METHODS) + " | ekf 3σ coverage |",
                  "|---|" + "---|" * (len(METHODS) + 1)]
        ratios = {h: [] for h in range(2)}
        for motion, radius in CASES:
            res = table[(grade, motion, radius)]
            cells = []
            med = {}
            for m in METHODS:
                e = np.median(np.array([r["e"] for r in res[m]]), axis=0) * 1e3
                med[m] = e
                cells.append(" / ".join(f"{x:.1f}" for x in e))
            cov = np.mean([r["coverage"] for r in res["ekf"]])
            lines.append(f"| {motion}, {radius * 100:.0f} cm | " + " | ".join(cells) + f" | {100 * cov:.0f} % |")
            for h in range(2):
                ratios[h].append(med["ekf"][h] / max(med["paper-ekf"][h], 1e-9))
        lines += ["", f"Median `ekf` / `paper-ekf` ratio: {np.median(ratios[0]):.2f} at 30 ms, "
                  f"{np.median(ratios[1]):.2f} at 180 ms (issue 21's goal: <= 0.6).", ""]
    # what a fingertip lag set wrong costs: the source's is 3 ms (MujocoScenario.lag_tau_s)
    lines += ["## A fingertip lag set wrong", "",
              "`ekf` on the 12 cm arcs, encoder grade, with `estimator.fingertip_lag_s` set to other values than "
              "the source's 3 ms (medians over the seeds, mm):", "",
              "| fingertip_lag_s | arc 30 ms / 180 ms / end | arc-turning 30 ms / 180 ms / end |", "|---|---|---|"]
    recs = {m: [generate(MujocoScenario(motion=m, radius=0.12, seed=s, **GRADES["encoder"]))
                for s in range(1, args.seeds + 1)] for m in ("arc", "arc-turning")}
    for lag in LAGS_S:
        cells = []
        for m, pairs in recs.items():
            e = np.median([evaluate(Recording.from_fields(f), tr, "ekf", fingertip_lag_s=lag)["e"] for f, tr in pairs],
                          axis=0) * 1e3
            cells.append(" / ".join(f"{x:.1f}" for x in e))
        lines.append(f"| {lag * 1e3:g} ms | " + " | ".join(cells) + " |")
    lines.append("")
    detected = [x for x in lat if x is not None]
    lines += ["## The accelerometer trigger on these recordings", "",
              f"Detected in {len(detected)} of {len(lat)} encoder-grade recordings"
              + (f", median {np.median(detected) * 1e3:.0f} ms from the true onset" if detected else "")
              + ": the onset is when the arm starts to push the held handle; the trigger fires on the "
              "fingertip's response to it.", "",
              f"Run time {time.time() - t0:.0f} s."]
    text = "\n".join(lines) + "\n"
    (ROOT / "benchmarks" / "mujoco.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
