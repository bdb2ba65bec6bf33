"""`tecdard sim-record OUT.npz`: a simulated scenario written as a recording with its truth (truth_* keys):
sim/scenarios.py's signal model, or (--engine mujoco) rigid-body physics (sim/mujoco_source.py)."""
from __future__ import annotations

import argparse
import dataclasses
import sys


def add_parser(sub) -> None:
    p = sub.add_parser("sim-record", help="write a simulated scenario as a recording with truth_* keys")
    p.add_argument("out", help="OUT.npz")
    p.add_argument("--engine", choices=("scenarios", "mujoco"), default="scenarios",
                   help="scenarios: sim/scenarios.py's signal model (default); mujoco: rigid-body physics of the "
                        "paper cutter, a pen on its tip or a block on a table edge (sim/mujoco_source.py, the bench extra)")
    p.add_argument("--motion", choices=("arc", "arc-turning", "push", "slip", "circle", "tilt", "ongoing"),
                   help="with --engine mujoco: the TCP's path (default arc); slip: the arc, the grasp slipping "
                        "on the handle; circle: the pen on its tip; tilt: a block tipped on its edge; ongoing: "
                        "the block slid into the edge at speed, then tipped")
    _scenario_options(p)
    p.set_defaults(func=main)


def main(args) -> int:
    """sim-record: sim/scenarios.py's signal model, or (--engine mujoco) the cutter or the pen in
    MuJoCo's physics (sim/mujoco_source.py), from the options the engine's scenario has."""
    from tecdard.recording.format import Recording, save_recording
    if args.engine == "mujoco":
        try:
            import mujoco  # noqa: F401

            from tecdard.sim.mujoco_source import MujocoScenario as Scenario, generate
        except ImportError:
            print("tecdard sim-record: --engine mujoco needs mujoco: pip install 'tecdar[bench]'", file=sys.stderr)
            return 2
    else:
        from tecdard.sim.scenarios import Scenario, generate
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(Scenario)
              if f.name != "extra" and getattr(args, f.name, None) is not None}
    try:
        sc = Scenario(**values)
        fields, truth = generate(sc)
    except ValueError as exc:
        print(f"tecdard sim-record: {exc}", file=sys.stderr)
        return 2
    rec = Recording.from_fields(fields)
    save_recording(args.out, rec, truth)
    what = f"mujoco {sc.motion}" if args.engine == "mujoco" else sc.kind
    print(f"wrote {args.out}: {what}, {len(rec.imu_t)} IMU samples at {sc.imu_hz:g} Hz, "
          f"{len(rec.tcp_t)} TCP samples at {sc.tcp_hz:g} Hz, onset at {float(truth['onset_t']):.4f} s")
    return 0


def _scenario_options(p) -> None:
    """One option per Scenario field, typed from its default."""
    from tecdard.sim.scenarios import KINDS, Scenario

    def vec(text: str):
        try:
            return tuple(float(x) for x in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None

    def flag(text: str) -> bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")

    for f in dataclasses.fields(Scenario):
        if f.name == "extra":
            continue
        opt = "--" + f.name.replace("_", "-")
        default = f.default
        if f.name == "kind":
            p.add_argument(opt, choices=KINDS, default=None, help=f"scenario (default {default})")
        elif isinstance(default, bool) or f.name == "tcp_rotates":
            p.add_argument(opt, type=flag, default=None, metavar="BOOL", help=f"default {default}")
        elif isinstance(default, int) and not isinstance(default, bool):
            p.add_argument(opt, type=int, default=None, help=f"default {default}")
        elif isinstance(default, str):
            p.add_argument(opt, default=None, help=f"default {default!r}")
        elif isinstance(default, tuple):
            p.add_argument(opt, type=vec, default=None, metavar="X,Y,Z", help=f"default {','.join(map(str, default))}")
        else:
            p.add_argument(opt, type=float, default=None, help=f"default {default}")
