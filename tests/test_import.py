"""Issue 48 §6: `tecdard import` turns logs labs already have into tecdar-recording/1. Bags written with
rosbags (sqlite3 and MCAP storage, and a bare MCAP file) holding sensor_msgs/Imu with JointState or
/tf, and CSVs with a YAML map, hostile rows among them; `localize` and `calibrate-mount` then run on
the result."""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from tecdard.control.geometry import matrix_to_quat, quat_to_matrix
from tecdard.control.mount_fit import rotation_angle_deg
from tecdard.recording.format import load_recording
from tests.conftest import tecdard

pytestmark = pytest.mark.slow

pytest.importorskip("rosbags")

IMU_HZ, JOINT_HZ = 500.0, 100.0
MOUNT = (0.0, 0.0, math.sin(math.radians(10.0)), math.cos(math.radians(10.0)))     # 20 deg about z


def _panda_motion(seconds: float = 12.0):
    """A Panda's wrist joints swept (every TCP axis turns), its TCP from Pinocchio, and what an IMU
    mounted MOUNT in the TCP reads (rate and specific force, IMU frame)."""
    from tecdard.robots.model import ArmModel
    model = ArmModel("panda")
    q0 = np.array([0.0, -0.5, 0.0, -2.2, 0.0, 1.8, 0.8])
    t = np.arange(0.0, seconds, 1.0 / 1000.0)
    q = np.tile(q0, (len(t), 1))
    for j, f in ((4, 0.31), (5, 0.43), (6, 0.57)):
        q[:, j] += 0.35 * np.sin(2 * math.pi * f * t)
    R = np.empty((len(t), 3, 3))
    p = np.empty((len(t), 3))
    for k in range(len(t)):
        oM = model.fk(q[k])
        R[k], p[k] = oM.rotation, oM.translation
    from tecdard.control.mount_fit import _log
    w_body = _log(np.einsum("nji,njk->nik", R[:-1], R[1:])) * 1000.0           # TCP frame, mid-step
    R_mount = quat_to_matrix(np.array(MOUNT))
    gyro = w_body @ R_mount                                                       # IMU frame
    f = (np.array([0.0, 0.0, 9.81]) @ R[:-1]) @ R_mount
    return model, t, q, p, R, gyro, f


def _write_bag(path, storage: str, with_tf: bool = False, imu_topic="/fingertip/imu"):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    Imu, JointState = store.types["sensor_msgs/msg/Imu"], store.types["sensor_msgs/msg/JointState"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    V3, Q = store.types["geometry_msgs/msg/Vector3"], store.types["geometry_msgs/msg/Quaternion"]
    TF, TS, Tr = (store.types[n] for n in ("tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped",
                                           "geometry_msgs/msg/Transform"))
    model, t, q, p, R, gyro, f = _panda_motion()
    t0 = 1_700_000_000.0

    def stamp(x):
        ns = int(round((t0 + x) * 1e9))
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        ci = w.add_connection(imu_topic, Imu.__msgtype__, typestore=store)
        cj = w.add_connection("/joint_states", JointState.__msgtype__, typestore=store)
        ct = w.add_connection("/tf", TF.__msgtype__, typestore=store) if with_tf else None
        cov = np.zeros(9)
        for k in range(0, len(t) - 1, int(1000 / IMU_HZ)):
            msg = Imu(header=Header(stamp=stamp(t[k]), frame_id="imu"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                      orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=V3(x=gyro[k, 0], y=gyro[k, 1],
                                                                                            z=gyro[k, 2]),
                      angular_velocity_covariance=cov, linear_acceleration=V3(x=f[k, 0], y=f[k, 1], z=f[k, 2]),
                      linear_acceleration_covariance=cov)
            w.write(ci, int((t0 + t[k]) * 1e9), store.serialize_cdr(msg, Imu.__msgtype__))
        for k in range(0, len(t), int(1000 / JOINT_HZ)):
            msg = JointState(header=Header(stamp=stamp(t[k]), frame_id=""), name=list(model.joint_names),
                             position=q[k].copy(), velocity=np.zeros(0), effort=np.zeros(0))
            w.write(cj, int((t0 + t[k]) * 1e9), store.serialize_cdr(msg, JointState.__msgtype__))
            if ct is not None:
                # base -> link (the pose less a fixed tool) -> tool: a chain of two, one static in content
                tool = np.array([0.0, 0.0, 0.1])
                qq = matrix_to_quat(R[k])
                link_p = p[k] - R[k] @ tool
                tr1 = TS(header=Header(stamp=stamp(t[k]), frame_id="base"), child_frame_id="link",
                         transform=Tr(translation=V3(x=link_p[0], y=link_p[1], z=link_p[2]),
                                      rotation=Q(x=qq[0], y=qq[1], z=qq[2], w=qq[3])))
                tr2 = TS(header=Header(stamp=stamp(t[k]), frame_id="link"), child_frame_id="tool",
                         transform=Tr(translation=V3(x=tool[0], y=tool[1], z=tool[2]),
                                      rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))
                w.write(ct, int((t0 + t[k]) * 1e9), store.serialize_cdr(TF(transforms=[tr1, tr2]), TF.__msgtype__))
    return p, R


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_with_joint_states_imports_and_calibrates(tmp_path, storage):
    """JointState through the Panda's model: the TCP matches Pinocchio's, the IMU's samples are kept,
    the given mount goes in, and calibrate-mount on the import finds the IMU's true mount."""
    bag = tmp_path / f"bag_{storage}"
    p, R = _write_bag(bag, storage)
    out = tmp_path / "rec.npz"
    res = tecdard("import", bag, out, "--model", "panda", "--mount", "0,0,0,1")
    assert res.returncode == 0, res.stderr
    assert "500 Hz" in res.stdout and "100 Hz" in res.stdout
    rec = load_recording(out)
    assert np.allclose(rec.tcp_pos[0], p[0], atol=1e-9)
    assert rotation_angle_deg(quat_to_matrix(rec.tcp_quat[5]).T @ R[50]) < 1e-4
    cal = tecdard("calibrate-mount", "--json", out)
    fit = json.loads(cal.stdout.splitlines()[0])
    assert cal.returncode == 0, cal.stderr
    assert rotation_angle_deg(quat_to_matrix(np.array(fit["imu_in_tcp_quat"])).T @ quat_to_matrix(np.array(MOUNT))) < 0.3
    assert abs(fit["time_offset_ms"]) <= 1.0
    # with the calibrated mount the import says so, and localize reads it (no contact: no onset)
    res = tecdard("import", bag, out, "--model", "panda", "--mount", ",".join(map(str, MOUNT)),
                  "--time-offset-s", "0.0")
    assert res.returncode == 0 and np.allclose(load_recording(out).imu_in_tcp_quat, MOUNT)
    loc = tecdard("localize", out)
    assert "Traceback" not in loc.stderr


def test_tf_and_a_bare_mcap_file(tmp_path):
    bag = tmp_path / "bag_tf"
    p, R = _write_bag(bag, "mcap", with_tf=True)
    bare = tmp_path / "bare.mcap"
    shutil.copy(next(bag.glob("*.mcap")), bare)
    out = tmp_path / "tf.npz"
    res = tecdard("import", bare, out, "--tf", "base:tool")
    assert res.returncode == 0, res.stderr
    rec = load_recording(out)
    assert np.allclose(rec.tcp_pos[:3], p[[0, 10, 20]], atol=1e-9)
    bad = tecdard("import", bare, out, "--tf", "base:gripper")
    assert bad.returncode == 2 and "no chain of transforms from base to gripper" in bad.stderr
    assert "(frames: base, link, tool)" in bad.stderr


def test_bad_bags_and_topics_are_one_line(tmp_path):
    bag = tmp_path / "bag"
    _write_bag(bag, "sqlite3")
    out = tmp_path / "x.npz"
    cases = [
        (("import", bag, out), "give the arm"),                                          # joints, no model
        (("import", bag, out, "--model", "ur5"), "the model's joints are"),              # another arm's names
        (("import", bag, out, "--model", "panda", "--imu-topic", "/nope"), "/nope: is not in the log"),
        (("import", bag, out, "--model", "panda", "--imu-topic", "/joint_states"), "/joint_states: is a sensor_msgs"),
        (("import", tmp_path / "missing", out), "no such file"),
        (("import", bag, out, "--model", "panda", "--mount", "1,2,3"), "--mount: expected a unit quaternion"),
        (("import", bag, out, "--model", "panda", "--tf", "base"), "--tf: expected BASE:TOOL"),
    ]
    for args, said in cases:
        res = tecdard(*args)
        assert res.returncode == 2, (args, res.stdout)
        assert said in res.stderr and len(res.stderr.strip().splitlines()) == 1, (args, res.stderr)
        assert "Traceback" not in res.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\nnot really")
    res = tecdard("import", junk, out, "--model", "panda")
    assert res.returncode == 2 and "not a readable MCAP file" in res.stderr


def _csv_log(tmp_path):
    _, t, q, p, R, gyro, f = _panda_motion(4.0)
    imu = tmp_path / "imu.csv"
    imu.write_text("time_ms,gx,gy,gz,ax,ay,az\n" + "".join(
        f"{t[k] * 1e3:.6f},{math.degrees(gyro[k, 0])},{math.degrees(gyro[k, 1])},{math.degrees(gyro[k, 2])},"
        f"{f[k, 0] / 9.80665},{f[k, 1] / 9.80665},{f[k, 2] / 9.80665}\n" for k in range(0, len(t) - 1, 2)))
    tcp = tmp_path / "tcp.csv"
    quats = [matrix_to_quat(R[k]) for k in range(0, len(t), 10)]
    tcp.write_text("t,x,y,z,qw,qx,qy,qz\n" + "".join(
        f"{t[k]},{p[k, 0] * 1e3},{p[k, 1] * 1e3},{p[k, 2] * 1e3},{qq[3]},{qq[0]},{qq[1]},{qq[2]}\n"
        for k, qq in zip(range(0, len(t), 10), quats)))
    m = tmp_path / "map.yaml"
    m.write_text("imu:\n  file: imu.csv\n  time: {column: time_ms, unit: ms}\n"
                 "  gyro: {columns: [gx, gy, gz], unit: deg/s}\n  accel: {columns: [ax, ay, az], unit: g}\n"
                 "tcp:\n  file: tcp.csv\n  time: {column: t, unit: s}\n  position: {columns: [x, y, z], unit: mm}\n"
                 "  orientation: {columns: [qw, qx, qy, qz], convention: wxyz}\n")
    return m, imu, tcp, p, gyro


def test_csv_with_a_map_imports_in_si_units(tmp_path):
    m, imu, tcp, p, gyro = _csv_log(tmp_path)
    out = tmp_path / "csv.npz"
    res = tecdard("import", "--csv", m, out)
    assert res.returncode == 0, res.stderr
    rec = load_recording(out)
    assert np.allclose(rec.tcp_pos[1], p[10], atol=1e-9) and np.allclose(rec.gyro[3], gyro[6], atol=1e-9)
    assert abs(float(np.median(np.diff(rec.imu_t))) - 0.002) < 1e-9


@pytest.mark.parametrize("where,row,said", [
    ("imu", "1.0,x,0,0,0,0,1\n", "row 3, column 'gx': 'x' is not a finite number"),
    ("imu", "1.0,nan,0,0,0,0,1\n", "column 'gx': 'nan' is not a finite number"),
    ("imu", "1.0,1e999,0,0,0,0,1\n", "'1e999' is not a finite number"),
    ("imu", "1.0,0,0\n", "row 3 has 3 fields, the header 7"),
    ("tcp", "0.005,0,0,0,1,0,0,0,9\n", "has 9 fields, the header 8"),
    ("tcp", "0.005,0,0,0,2,0,0,0\n", "row 3: the orientation is no unit quaternion"),
])
def test_hostile_csv_rows_are_named(tmp_path, where, row, said):
    m, imu, tcp, p, gyro = _csv_log(tmp_path)
    f = imu if where == "imu" else tcp
    lines = f.read_text().splitlines(keepends=True)
    f.write_text(lines[0] + lines[1] + row + "".join(lines[2:]))
    res = tecdard("import", "--csv", m, tmp_path / "x.npz")
    assert res.returncode == 2 and said in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.npz").exists()


def test_csv_maps_that_are_wrong_are_named(tmp_path):
    m, imu, tcp, p, gyro = _csv_log(tmp_path)
    text = m.read_text()
    for broken, said in ((text.replace("unit: deg/s", "unit: rpm"), "imu.gyro.unit: expected one of rad/s, deg/s"),
                         (text.replace("[gx, gy, gz]", "[gx, gy]"), "imu.gyro.columns: expected 3 column names"),
                         (text.replace("column: t,", "column: when,"), "no column 'when'"),
                         (text.replace("convention: wxyz", "convention: euler"), "tcp.orientation.convention"),
                         ("[1, 2", "not a readable YAML map"), ("- a\n- b\n", "expected a mapping")):
        m.write_text(broken)
        res = tecdard("import", "--csv", m, tmp_path / "x.npz")
        assert res.returncode == 2 and said in res.stderr, (said, res.stderr)
    # times that go backwards
    m.write_text(text)
    lines = imu.read_text().splitlines(keepends=True)
    imu.write_text(lines[0] + lines[2] + lines[1] + "".join(lines[3:]))
    res = tecdard("import", "--csv", m, tmp_path / "x.npz")
    assert res.returncode == 2 and "does not follow" in res.stderr and "row 3" in res.stderr
