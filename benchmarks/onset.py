"""The onset trigger on both of our sources (issue 34); writes benchmarks/onset.md.

    python -m benchmarks.onset [--seeds N]

Replayed as `tecdard localize` replays (causal, the robot's states at their own rate), each
episode released 0.3 s after its detection so that every onset of a recording counts
(tecdard.recording.replay.replay_onsets):

- free air: sim/scenarios.py's `free_air` (Ruckig moves at 0.5 m/s^2 and 5 m/s^3 per axis, the
  tool turning at up to 0.5 rad/s; a rigid fingertip) and MuJoCo's `carry` (a 0.3 kg block held
  clear of the table, moved back and forth with starts and stops peaking at 0.5 m/s^2; MuJoCo's
  two-spring fingertip): false onsets per minute of motion;
- the arm already moving, then a contact: sim's `edge-ongoing` and MuJoCo's `ongoing` (the block
  slid into a ridge), at several speeds: the first onset against the true contact;
- a contact that exists before the arm moves, turned smoothly from rest (no click: sim's ring off;
  MuJoCo's hinge friction small): when the twist fires and where it dates the onset;
- early accuracy: the estimate 30 ms after the true onset, as localize gives it (the trigger's own
  onset), `ekf` beside `paper-ekf`, lever arms of 4, 8 and 12 cm and a pen, over seeds.

Each table says what the trigger of before (the raw accelerometer against its rest level, no
motion taken off) did on the same recordings.
"""
from __future__ import annotations

import argparse
import pathlib
import platform
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.config import Config  # noqa: E402
from tecdard.control.geometry import quat_to_matrix  # noqa: E402
from tecdard.control.pipeline import ContactPipeline  # noqa: E402
from tecdard.recording.format import Recording  # noqa: E402
from tecdard.sim import mujoco_source as M  # noqa: E402
from tecdard.sim.scenarios import FreeAirMoves, Scenario, free_air, generate  # noqa: E402
from tecdard.recording import replay as L  # noqa: E402

OUT = ROOT / "benchmarks" / "onset.md"
IMPACT_WITHIN_S = 0.005       # an onset this close to the true contact is on time
EARLY_S = 0.030


def pipeline(rec: Recording, method: str = "ekf", raw: bool = False, **estimator) -> ContactPipeline:
    pipe = ContactPipeline.from_config(Config({"estimator": estimator}).section("estimator"),
                                       quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz, method=method,
                                       plane_normal=rec.plane_normal)
    if raw:                     # the trigger of before: no motion taken off, no twist, no prediction
        pipe._explained = lambda t: None
        pipe.detector.twist_threshold = None
        pipe.detector.predictor.horizon_s = 0.0      # judged on the remainder itself
    return pipe


def motion_minutes(moves: np.ndarray) -> float:
    return float(np.sum(moves[:, 1] - moves[:, 0])) / 60.0


def free_air_rows(seeds: int) -> list[str]:
    rows = []
    for name, make in (
            ("sim `free_air`, 30 moves", lambda s: free_air(FreeAirMoves(moves=30, seed=s))),
            ("MuJoCo `carry` 20 mm/s", lambda s: M.generate(M.MujocoScenario(motion="carry", speed=0.02, move_s=8.0,
                                                                               radius=0.12, seed=s))),
            ("MuJoCo `carry` 50 mm/s", lambda s: M.generate(M.MujocoScenario(motion="carry", speed=0.05, move_s=8.0,
                                                                               radius=0.12, seed=s))),
            ("MuJoCo `carry` 100 mm/s", lambda s: M.generate(M.MujocoScenario(motion="carry", speed=0.1, move_s=8.0,
                                                                                radius=0.12, seed=s)))):
        minutes, new, old, kinds = 0.0, 0, 0, {}
        for seed in range(1, seeds + 1):
            fields, truth = make(seed)
            rec = Recording.from_fields(fields)
            minutes += motion_minutes(np.asarray(truth["moves"]))
            found = L.replay_onsets(rec, pipeline(rec))
            new += len(found)
            for e in found:
                kinds[e["trigger"]] = kinds.get(e["trigger"], 0) + 1
            old += len(L.replay_onsets(rec, pipeline(rec, raw=True)))
        by = ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"
        rows.append(f"| {name} | {minutes:.2f} | {new} ({by}) | {new / minutes:.1f} | {old} | {old / minutes:.1f} |")
    return rows


def first_onset(rec: Recording, raw: bool = False):
    found = L.replay_onsets(rec, pipeline(rec, raw=raw))
    return found[0] if found else None


def ongoing_rows(seeds: int) -> list[str]:
    rows = []
    cases = [(f"sim `edge-ongoing` {v * 1000:.0f} mm/s",
              lambda s, v=v: generate(Scenario(kind="edge-ongoing", radius=0.12, speed=v, seed=s, duration_s=0.5)))
             for v in (0.01, 0.02, 0.05)]
    cases += [(f"MuJoCo `ongoing` {v * 1000:.0f} mm/s",
               lambda s, v=v: M.generate(M.MujocoScenario(motion="ongoing", radius=0.12, speed=v, seed=s)))
              for v in (0.01, 0.02, 0.05)]
    for name, make in cases:
        res = {False: [], True: []}
        for seed in range(1, seeds + 1):
            fields, truth = make(seed)
            rec = Recording.from_fields(fields)
            on = float(truth["onset_t"])
            for raw in (False, True):
                e = first_onset(rec, raw)
                res[raw].append(np.nan if e is None else e["t"] - on)

        def cell(d):
            d = np.array(d)
            ok = np.abs(d) <= IMPACT_WITHIN_S
            early = d < -IMPACT_WITHIN_S
            missed = ~ok & ~early
            spread = f"{np.nanmin(d) * 1e3:+.1f} to {np.nanmax(d) * 1e3:+.1f}" if np.isfinite(d).any() else "-"
            return f"{spread} | {int(ok.sum())}/{len(d)} | {int(early.sum())} | {int(missed.sum())}"
        rows.append(f"| {name} | {cell(res[False])} | {cell(res[True])} |")
    return rows


def from_rest_rows(seeds: int) -> list[str]:
    rows = []
    cases = [(f"sim `edge-arc` {r * 100:.0f} cm",
              lambda s, r=r: generate(Scenario(kind="edge-arc", radius=r, seed=s, tcp_hz=500.0, ring_gain=0.0,
                                               duration_s=0.5))) for r in (0.04, 0.08, 0.12)]
    cases += [("sim pen 14 cm", lambda s: generate(Scenario(kind="point-circle", radius=0.14, speed=0.03, seed=s,
                                                            tcp_hz=500.0, ring_gain=0.0, duration_s=0.5)))]
    cases += [(f"MuJoCo `arc` {r * 100:.0f} cm", lambda s, r=r: M.generate(M.MujocoScenario(motion="arc", radius=r,
                                                                                           seed=s)))
              for r in (0.04, 0.08, 0.12)]
    cases += [("MuJoCo pen 14 cm", lambda s: M.generate(M.MujocoScenario(motion="circle", radius=0.14, speed=0.03,
                                                                         seed=s)))]
    for name, make in cases:
        dated, detected, kinds, old = [], [], set(), []
        for seed in range(1, seeds + 1):
            fields, truth = make(seed)
            rec = Recording.from_fields(fields)
            on = float(truth["onset_t"])
            e = first_onset(rec)
            if e is not None:
                dated.append(e["t"] - on)
                detected.append(e["detected_t"] - on)
                kinds.add(e["trigger"])
            o = first_onset(rec, raw=True)
            old.append(np.nan if o is None else o["t"] - on)
        fmt = (lambda d: f"{np.min(d) * 1e3:.0f}-{np.max(d) * 1e3:.0f}" if len(d) else "none")
        old = np.array(old)
        old_cell = f"{np.nanmin(old) * 1e3:.0f}-{np.nanmax(old) * 1e3:.0f}" if np.isfinite(old).any() else "none"
        rows.append(f"| {name} | {len(dated)}/{seeds} | {'/'.join(sorted(kinds)) or '-'} | {fmt(detected)} | "
                    f"{fmt(dated)} | {old_cell} |")
    return rows


def error_at(rows: np.ndarray, truth: dict, t: float) -> tuple[float, bool]:
    """(the in-plane error (3D for a point), m, of the first estimate at or after t since the true
    onset; whether its 3 sigma covers the error on every observable axis)."""
    if len(rows) == 0:
        return np.nan, False
    since = rows[:, 0] - float(truth["onset_t"])
    k = int(np.searchsorted(since, t))
    if k >= len(rows):
        return np.nan, False
    d = rows[k, 1:4] - truth["p_c"]
    a = np.asarray(truth["axis"], float)
    if np.linalg.norm(a) > 0:
        d = d - (d @ a) * a
    std = rows[k, 4:7]
    observable = std < 0.1                        # the unobservable edge direction reports 0.5 m
    return float(np.linalg.norm(d)), bool(np.all((np.abs(d) <= 3 * std) | ~observable))


def early_rows(seeds: int) -> list[str]:
    rows = []
    cases = [(f"sim arc {r * 100:.0f} cm", lambda s, r=r: generate(Scenario(kind="edge-arc", radius=r, seed=s,
                                                                               duration_s=0.5)))
             for r in (0.04, 0.08, 0.12)]
    cases += [("sim pen 14 cm", lambda s: generate(Scenario(kind="point-circle", radius=0.14, speed=0.03, seed=s,
                                                            duration_s=0.5)))]
    cases += [("sim ongoing 12 cm", lambda s: generate(Scenario(kind="edge-ongoing", radius=0.12, seed=s,
                                                                duration_s=0.5)))]
    cases += [(f"MuJoCo arc {r * 100:.0f} cm", lambda s, r=r: M.generate(M.MujocoScenario(motion="arc", radius=r,
                                                                                         seed=s, move_s=0.5)))
              for r in (0.04, 0.08, 0.12)]
    cases += [("MuJoCo pen 14 cm", lambda s: M.generate(M.MujocoScenario(motion="circle", radius=0.14, speed=0.03,
                                                                         seed=s, move_s=0.5)))]
    cases += [("MuJoCo ongoing 12 cm", lambda s: M.generate(M.MujocoScenario(motion="ongoing", radius=0.12, seed=s,
                                                                             move_s=0.5)))]
    for name, make in cases:
        errs, covers = {"ekf": [], "paper-ekf": []}, {"ekf": 0, "paper-ekf": 0}
        for seed in range(1, seeds + 1):
            fields, truth = make(seed)
            rec = Recording.from_fields(fields)
            lag = {"fingertip_lag_s": 0.0} if "sim" in name else {}
            for method in errs:
                out, _, _ = L.replay(rec, pipeline(rec, method, **lag), 1000.0)
                e, covered = error_at(out, truth, EARLY_S)
                errs[method].append(e * 1e3)
                covers[method] += covered

        def cell(method):
            e = np.array(errs[method])
            if not np.isfinite(e).any():
                return "no estimate | -"
            return f"{np.nanmedian(e):.1f} [{np.nanmin(e):.1f}-{np.nanmax(e):.1f}] | {covers[method]}/{seeds}"
        rows.append(f"| {name} | {cell('ekf')} | {cell('paper-ekf')} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    started = time.perf_counter()
    parts = [
        "# The onset trigger (issue 34)", "",
        f"`python -m benchmarks.onset --seeds {args.seeds}` on {platform.machine()}, Python "
        f"{platform.python_version()}. Causal replays as `tecdard localize` runs them; each episode released "
        "0.3 s after its detection, the trigger then settling and re-arming as the daemon's does. \"Before\": the "
        "raw accelerometer against its rest level (the trigger of before this issue).", "",
        "## Free air: false onsets", "",
        "| recording (seeds) | minutes of motion | onsets (by trigger) | per minute | before | before, per minute |",
        "|---|---|---|---|---|---|", *free_air_rows(args.seeds), "",
        "MuJoCo's `carry` block swings in the two-spring fingertip (4 Hz, up to 0.3 rad/s of twist on a 0.5 m/s² "
        "start, as much as a grasped hinge's): the twist fires only once it has held one way for 0.2 s, and a "
        "swing turns back within half its period (docs/estimation.md). \"Before\" here: the raw accelerometer "
        "fired on the first start, and did not settle again between moves.", "",
        "## The arm already moving, then a contact", "",
        f"First onset against the true contact, ms; on time within ±{IMPACT_WITHIN_S * 1e3:.0f} ms; early (before the "
        "contact: a false onset that took the episode) and missed.", "",
        "| recording | now: first onset, ms | on time | early | missed | before: first onset, ms | on time | early "
        "| missed |", "|---|---|---|---|---|---|---|---|---|", *ongoing_rows(args.seeds), "",
        "## A contact that exists, turned smoothly from rest (no click)", "",
        "ms after the arm's start: when the trigger fired, and where it dated the onset.", "",
        "| recording | found | trigger | detected, ms | dated, ms | before: onset, ms |", "|---|---|---|---|---|---|",
        *from_rest_rows(args.seeds), "",
        "## Early accuracy: 30 ms after the true onset", "",
        "In-plane error (3D for the pen), mm: median [range] over seeds, each method behind the same trigger "
        "(`tecdard localize --method`); and in how many seeds the estimate's 3σ covered its error then.", "",
        "| recording | ekf | 3σ covers | paper-ekf | 3σ covers |", "|---|---|---|---|---|", *early_rows(args.seeds),
        "",
        f"({time.perf_counter() - started:.0f} s)", ""]
    OUT.write_text("\n".join(parts))
    print("\n".join(parts))


if __name__ == "__main__":
    main()
