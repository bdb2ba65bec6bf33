"""The members of a recording (`tecdar-recording/1`), declared once: the reader, the writer and the checks of
recording/format.py all go through this table, and docs/recordings.md's tables are this table rendered
(tests/test_layout.py holds them equal). Adding a member is a row here, its producer, and a test."""
from __future__ import annotations

from dataclasses import dataclass

MAX_IMU_SAMPLES = 12_000_000     # 30 min at 6.7 kHz
MAX_TCP_SAMPLES = 4_000_000      # an hour at 1 kHz

# the length a shape's symbolic rows stand for: N the IMU's samples, M the proprioception's
ROWS_OF = {"N": "imu_t", "M": "tcp_t"}


@dataclass(frozen=True)
class Member:
    """One key of the archive. `shape` names its rows symbolically ("N": as imu_t, "M": as tcp_t, "B",
    "K", "T": any number, "n": the arm's joints, "1+n": a time and the joints); `kind` is "array" (numbers), "string" (a string scalar) or
    "json" (a string scalar holding a JSON list or object)."""
    key: str
    shape: tuple
    required: bool
    meaning: str
    kind: str = "array"
    field: str | None = None      # the Recording's (or LiveLog's) attribute, where it is not the key
    rows_max: int | None = None   # a time series' own bound, refused before it is read

    @property
    def attr(self) -> str:
        return self.field or self.key.removeprefix("live_")

    @property
    def rows_of(self) -> str | None:
        """The key whose length this member's rows must equal (None: its rows are its own)."""
        of = ROWS_OF.get(self.shape[0]) if self.shape else None
        return None if of == self.key else of

    def shape_text(self) -> str:
        if self.kind == "json" and self.key.startswith("live_"):
            return "JSON list"
        if self.kind != "array":
            return "() str"
        return "(" + ",".join(str(s) for s in self.shape) + ("," if len(self.shape) == 1 else "") + ")"

    def row(self) -> str:
        """The member as a row of docs/recordings.md's tables: key, shape, required, meaning."""
        return f"| `{self.key}` | {self.shape_text()} | {'yes' if self.required else 'no'} | {self.meaning} |"


# What every recording has or may have, in the order the reader checks them (its first error names
# the first bad key in this order).
CORE = (
    Member("format", (), True, "exactly `tecdar-recording/1`", kind="string"),
    Member("imu_t", ("N",), True, "sample times, seconds, strictly increasing", rows_max=MAX_IMU_SAMPLES),
    Member("gyro", ("N", 3), True, "angular rate in the IMU sensor frame, rad/s, raw (not bias-corrected, not "
                                   "scaled by eta)"),
    Member("accel", ("N", 3), True, "specific force in the IMU sensor frame, m/s^2 (gravity included)"),
    Member("tcp_t", ("M",), True, "proprioception times, same clock as `imu_t`, strictly increasing",
           rows_max=MAX_TCP_SAMPLES),
    Member("tcp_pos", ("M", 3), True, "TCP position in the world frame, m"),
    Member("tcp_quat", ("M", 4), True, "TCP orientation, unit quaternion (x, y, z, w), world <- TCP"),
    Member("imu_in_tcp_quat", (4,), True, "fixed mount rotation of the IMU, (x, y, z, w), TCP <- IMU"),
    Member("grip_force", ("M",), False, "grasp force, N (drives eta scheduling when present)"),
    Member("tcp_vel", ("M", 3), False, "TCP linear velocity in the world frame, m/s, as the robot reports it (many "
                                       "controllers do, at their own rate); when absent, estimators derive it "
                                       "from `tcp_pos`"),
    Member("plane_normal", (3,), False, "unit vector, world frame: when present the interaction is planar about "
                                        "this axis and a planar estimator may be used"),
    Member("meta", (), False, "JSON object: free-form rig description (robot, tool, notes)", kind="json"),
)

# What a daemon's recording adds: how its live estimator was fed (recording/live.py's LiveLog), so
# that a replay is the live answer.
LIVE = (
    Member("live_pass_end", ("B",), True, "IMU rows fed to the pipeline up to the end of each estimator pass",
           rows_max=MAX_IMU_SAMPLES),
    Member("live_tcp_pass", ("M",), True, "the pass before which each proprioception sample reached the pipeline"),
    Member("live_tcp_w", ("M", 3), True, "the TCP's angular rate as reported, rad/s, world"),
    Member("live_changes", (), True, "`{pass, directive, odr_hz, saturation}` wherever the control thread's "
                                     "directive (episode, trigger armed, arc following, bias held, commanded "
                                     "onset), the IMU data rate or the clipping points changed", kind="json"),
    Member("live_bias0", (4,), True, "the gyro bias at the first pass (rad/s, IMU frame) and the rest time "
                                     "averaged into it (s)"),
    Member("live_est", ("K", 7), True, "the live estimates: `t, px, py, pz, sx, sy, sz`"),
    Member("live_axis", ("K", 3), False, "the rotation axis (world, unit) with each of `live_est`'s estimates; NaN "
                                         "until the motion excites it", field="axis"),
    Member("live_events", (), True, "the pipeline's and the daemon's events during the capture (task start and "
                                    "end, faults, stops)", kind="json"),
    Member("live_q", ("M", "n"), False, "the measured joints at each proprioception sample, rad (the export "
                                        "draws the arm from it)"),
    Member("live_qd", ("M", "n"), False, "the joints' measured rates at each proprioception sample, rad/s (with "
                                         "`live_q`: a dataset's state)"),
    Member("live_gripper", ("M", 2), False, "the gripper at each proprioception sample: its opening (m) and whether "
                                            "it held something (1 or 0); -1 where it could not say "
                                            "(`meta.grip_force_source` says where `grip_force` came from)"),
    Member("tcp_wrench", ("M", 6), False, field="wrench", meaning="the arm's own estimate of the external wrench at the TCP at each "
                                          "proprioception sample: force (N) then torque (N m), world frame; NaN "
                                          "where the arm gives none. `meta.wrench_source` says whose estimate: "
                                          "`actual_TCP_force` (UR), `O_F_ext_hat_K` or `joint_torques` (Franka), "
                                          "`sim_contact` (the simulator: force only)"),
    Member("live_cmd", ("T", "1+n"), False, field="cmd", meaning="each control tick's command: its time (s, the "
                                            "samples' clock), then the joint rates sent to the arm (rad/s; zeros "
                                            "where the tick held it): a dataset's action, and what the replayed "
                                            "onset trigger asks of the arm's own steps", rows_max=MAX_TCP_SAMPLES),
)

MEMBERS = {m.key: m for m in CORE + LIVE}
TRUTH_PREFIX = "truth_"          # a simulator's truth (benchmarks and tests; estimators never see it)


def table(members: tuple[Member, ...]) -> str:
    """The members as a table of docs/recordings.md: key, shape, required, meaning."""
    return "\n".join(["| key | shape | required | meaning |", "|---|---|---|---|", *(m.row() for m in members)])
