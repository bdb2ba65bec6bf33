"""`tecdard calibrate-mount REC.npz...`: the IMU's rotation in the TCP frame, the board's clock against
the arm's and the gyro's scale, fitted from a recording of free motion (control/mount_fit.py).

The gyro is fitted against the arm's own rate from its recorded TCP attitudes (the forward
kinematics): nothing may turn the fingertip relative to the gripper meanwhile (no contact). Each
recording is fitted alone; with several, their mean is printed too. What is printed:
- the rotation, (x, y, z, w) TCP <- IMU, and how far it is from the recording's configured mount;
- the time offset, ms, with its one sigma, and the gyro's scale;
- the residual at the states' rate, and the IMU's rate above the states' band that the encoders do
  not see (the arm's vibration), apart from the chip's white noise;
- the config lines to paste.

Refused in one line (exit 2): a file that is not a recording, and a motion that did not turn the TCP
about every axis (then record small rotations about each TCP axis, as --live does).
"""
from __future__ import annotations

import json
import math
import sys

import numpy as np

from tecdard.safejson import show
from tecdard.tools import mount_live


def add_parser(sub) -> None:
    p = sub.add_parser("calibrate-mount", help="the IMU's mount, clock offset and gyro scale from free motion",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("recordings", nargs="*", help="REC.npz ... of free motion (nothing touched)")
    p.add_argument("--max-offset-ms", type=float, default=50.0,
                   help="the clock offsets tried: within +- this, ms (default 50; 1..500)")
    p.add_argument("--json", action="store_true", help="one JSON object per recording, and the mean")
    mount_live.add_options(p)
    p.set_defaults(func=main)


def _one(path: str, max_offset_s: float) -> dict:
    from tecdard.control.geometry import quat_to_matrix
    from tecdard.control.mount_fit import fit_mount
    from tecdard.recording.format import load_recording
    rec = load_recording(path)
    fit = fit_mount(rec.imu_t, rec.gyro, rec.tcp_t, rec.tcp_quat, max_offset_s=max_offset_s)
    configured = quat_to_matrix(np.asarray(rec.imu_in_tcp_quat, float))
    applied = float((rec.meta or {}).get("imu_time_offset_s", 0.0) or 0.0)
    return {"recording": path, "imu_in_tcp_quat": [round(float(x), 6) for x in fit.quat],
            "degrees_from_configured": round(fit.angle_from_deg(configured), 3),
            "configured_quat": [round(float(x), 6) for x in rec.imu_in_tcp_quat],
            "time_offset_ms": round(fit.offset_s * 1e3, 2), "time_offset_sigma_ms": round(fit.offset_sigma_s * 1e3, 2),
            "time_offset_applied_ms": round(applied * 1e3, 3),
            "gyro_scale": round(fit.scale, 4), "gyro_bias_rad_s": [round(float(x), 5) for x in fit.bias],
            "residual_rad_s": round(fit.residual_rad_s, 5), "vibration_rad_s": round(fit.vibration_rad_s, 5),
            "noise_rad_s": round(fit.noise_rad_s, 5),
            "excitation_rad_s": [round(float(x), 4) for x in fit.excitation_rad_s], "intervals": fit.intervals}


def _mean(results: list[dict]) -> dict:
    """The mean mount (the quaternions' principal eigenvector) and offset over recordings, with the spread."""
    q = np.array([r["imu_in_tcp_quat"] for r in results])
    q = q * np.sign(q @ q[0])[:, None]
    w, v = np.linalg.eigh(q.T @ q)
    mean_q = v[:, -1] * np.sign(v[:, -1] @ q[0])
    offsets = np.array([r["time_offset_ms"] + r["time_offset_applied_ms"] for r in results])
    spread = [2.0 * math.degrees(math.acos(min(1.0, abs(float(mean_q @ qi))))) for qi in q]
    return {"recording": "mean", "imu_in_tcp_quat": [round(float(x), 6) for x in mean_q],
            "spread_deg": round(max(spread), 3), "time_offset_ms": round(float(offsets.mean()), 2),
            "time_offset_spread_ms": round(float(offsets.std(ddof=1)) if len(offsets) > 1 else 0.0, 2),
            "gyro_scale": round(float(np.mean([r["gyro_scale"] for r in results])), 4)}


def _print(r: dict) -> None:
    print(f"{r['recording']}: mount {r['imu_in_tcp_quat']} (x, y, z, w; TCP <- IMU), "
          f"{r['degrees_from_configured']:.2f} deg from the configured {r['configured_quat']}")
    applied = r["time_offset_applied_ms"]
    after = f" (after the {applied:g} ms configured)" if applied else ""
    print(f"  clock: the IMU's stamps {r['time_offset_ms']:+.1f} ± {r['time_offset_sigma_ms']:.1f} ms against the "
          f"arm's states'{after}")
    print(f"  gyro scale {r['gyro_scale']:.4f}; residual {r['residual_rad_s']:.4f} rad/s RMS at the states' rate; "
          f"above their band {r['vibration_rad_s']:.4f} rad/s of vibration the encoders do not see and "
          f"{r['noise_rad_s']:.4f} rad/s of the chip's noise per sample")
    print(f"  motion: {', '.join(f'{x:.3f}' for x in r['excitation_rad_s'])} rad/s RMS about its principal axes, "
          f"{r['intervals']} intervals")
    if abs(r["gyro_scale"] - 1.0) > 0.03:
        print(f"  the gyro's scale is {abs(r['gyro_scale'] - 1.0) * 100:.0f} % off 1 (the chip is trimmed to 1 %): "
              "check imu.serial.gyro_fs_dps")


def _config_lines(quat, offset_ms: float) -> str:
    return ("imu:\n"
            f"  imu_in_tcp_quat: [{', '.join(f'{x:.6f}' for x in quat)}]   # fitted by tecdard calibrate-mount\n"
            f"  time_offset_s: {offset_ms / 1e3:.4f}              # the IMU's stamps less the arm's states'")


def main(args) -> int:
    """`tecdard calibrate-mount`: the fit per recording, the mean, the config lines; exit 2 with one line."""
    from tecdard.control.mount_fit import ExcitationError
    from tecdard.recording.format import RecordingError

    if not 1.0 <= args.max_offset_ms <= 500.0:
        print(f"tecdard calibrate-mount: --max-offset-ms: expected 1..500 ms, got {args.max_offset_ms:g}",
              file=sys.stderr)
        return 2
    paths = list(args.recordings)
    if args.live == bool(paths):
        print("tecdard calibrate-mount: give recordings of free motion, or --live (not both)", file=sys.stderr)
        return 2
    if args.live:
        if not (1.0 <= args.amplitude_deg <= 10.0 and 1.0 <= args.rate_deg_s <= 20.0):
            print(f"tecdard calibrate-mount: --amplitude-deg must be 1..10 and --rate-deg-s 1..20, got "
                  f"{args.amplitude_deg:g} and {args.rate_deg_s:g}", file=sys.stderr)
            return 2
        code, path = mount_live.record(args)
        if code:
            return code
        if path is None:
            print("tecdard calibrate-mount --live: the daemon wrote no recording of the turns", file=sys.stderr)
            return 1
        print(f"calibrate-mount --live: recorded {path}", file=sys.stderr)
        paths = [path]
    results = []
    for path in paths:
        try:
            results.append(_one(path, args.max_offset_ms / 1e3))
        except (RecordingError, ExcitationError) as exc:
            said = str(exc)
            name = show(path, 200)
            print(f"tecdard calibrate-mount: {said if said.startswith(name) else f'{name}: {said}'}", file=sys.stderr)
            return 2
    mean = _mean(results) if len(results) > 1 else None
    if args.json:
        for r in results + ([mean] if mean else []):
            print(json.dumps(r))
        return 0
    for r in results:
        _print(r)
    final = mean or results[0]
    if mean:
        print(f"mean of {len(results)}: mount {mean['imu_in_tcp_quat']} (spread {mean['spread_deg']:.2f} deg), "
              f"clock {mean['time_offset_ms']:+.1f} ms (spread {mean['time_offset_spread_ms']:.1f} ms)")
    offset = final["time_offset_ms"] + (0.0 if mean else final["time_offset_applied_ms"])
    print("\nconfig lines to paste:\n" + _config_lines(final["imu_in_tcp_quat"], offset))
    return 0
