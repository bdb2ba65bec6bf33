"""Simulator speed (issue 4): 10 s of simulated scenario, as fast as possible; writes benchmarks/sim.md."""
from __future__ import annotations

import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.sim.imu import SimImu, SimImuParams  # noqa: E402
from tecdard.robots.model import READY_Q, ArmModel  # noqa: E402
from tecdard.sim.scenarios import Scenario, generate  # noqa: E402
from tecdard.sim.robot import SimRobot, SimRobotParams  # noqa: E402
from tecdard.sim.world import HingeParams, HingeWorld, PivotParams, PivotWorld, mapping_scene  # noqa: E402

SIM_S = 10.0
TICK_S = 0.02


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def live(world_name: str) -> float:
    """Wall seconds for SIM_S of the live simulator (1 kHz arm + world + 6667 Hz IMU), driven by a 20 ms loop."""
    arm = ArmModel("panda")
    q_home = np.array(READY_Q["panda"])
    if world_name == "hinge":
        factory = lambda p, R: HingeWorld(HingeParams(p - np.array([0.15, 0, 0]), np.array([0, 1.0, 0])), p)  # noqa
    else:
        factory = lambda p, R: PivotWorld(PivotParams(np.array([0, 0, 0.12]), mapping_scene()), p, R)  # noqa
    clock = Clock()
    imu = SimImu(SimImuParams(), seed=0)
    robot = SimRobot(arm, SimRobotParams(q_home=q_home), factory, imu, seed=0, clock=clock)
    t0 = time.perf_counter()
    for k in range(int(SIM_S / TICK_S)):
        js = robot.read_state()
        oM = arm.fk(js.q)
        v = np.array([0.0, 0.0, 0.02 if (k // 100) % 2 == 0 else -0.02])
        robot.command_joint_velocity(arm.dls_velocity(js.q, arm.servo_twist(oM, oM.translation, v, oM.rotation,
                                                                             np.zeros(3)), q_home))
        clock.t += TICK_S
        robot.advance_to(clock.t)
        while imu.read(0.0) is not None:
            pass
    return time.perf_counter() - t0


def offline(kind: str) -> float:
    t0 = time.perf_counter()
    generate(Scenario(kind=kind, duration_s=SIM_S, rest_s=0.5))
    return time.perf_counter() - t0


def main() -> int:
    lines = ["# Simulator speed", "", f"{SIM_S:.0f} s of simulated time, as fast as possible:", ""]
    for w in ("hinge", "scene"):
        el = live(w)
        lines.append(f"- live robot (Panda, 1 kHz physics, 6667 Hz fingertip IMU) with the {w} world: "
                     f"{el:.2f} s wall ({SIM_S / el:.1f}x real time)")
    for kind in ("edge-arc", "point-circle", "hinge"):
        el = offline(kind)
        lines.append(f"- offline recording `{kind}` (vectorised): {el:.2f} s wall ({SIM_S / el:.0f}x real time)")
    (ROOT / "benchmarks" / "sim.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
