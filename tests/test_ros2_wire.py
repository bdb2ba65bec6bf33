"""The ROS 2 node's bytes against real ROS 2 code (issue 36): rclpy's serialisation reads our CDR and we
read rclpy's, our RIHS01 hashes are rosidl's (its generator, its JSON and the generated type supports'
own), and the rmw_zenoh conventions (keys, tokens, QoS strings, attachment) read back field by field,
also by zenoh-ros2-sdk's independent parsers."""
import ctypes
import importlib
import json
import math
import pathlib
import sys

import numpy as np
import pytest

from tecdard import verbs as task_verbs
from tecdard.api import commands as C
from tecdard.ros2 import messages as M
from tecdard.ros2 import rmw
from tecdard.runtime.ros2_node import TOPICS, TRIGGER, TRIGGER_SRV, _BlockAverage
from tecdard.ros2.typesupport import HASH_NOT_SUPPORTED, MSGS_DIR, TypeSupport, dds_type_name
from tests.fakes.ros2_client import TFMESSAGE_MSG

serialization = pytest.importorskip("rclpy.serialization", reason="ros-rclpy is installed by `make test`")
SHARE = pathlib.Path(sys.prefix) / "share"
LONG_FRAME = "frame_" + "x" * 5000
STOCK = [t for t, _ in TOPICS.values() if not t.startswith(("tecdar_msgs", "tf2_msgs"))]


@pytest.fixture(scope="module")
def ts():
    from tecdard.ros2.parameters import SRV_TEXTS
    support = TypeSupport("kilted")
    support.add_service(TRIGGER_SRV, TRIGGER)
    for srv_type, text in SRV_TEXTS.items():
        support.add_service(text, srv_type)
    from tecdard.ros2 import type_description as TD
    support.add_service(TD.SRV_TEXT, TD.SERVICE)
    return support


class Est:
    """A ContactEstimate's fields as the node reads them."""
    def __init__(self, p, std, cov, axis, converged=True, t=12.5):
        self.p, self.std, self.cov, self.axis, self.converged, self.t = (np.array(p, float), np.array(std, float),
                                                                          np.array(cov, float), axis, converged, t)


ESTIMATES = [
    Est([0.31, -0.02, 0.45], [0.001, 0.002, 0.0005], np.diag([1e-6, 4e-6, 2.5e-7]), np.array([0.0, 1.0, 0.0])),
    Est([0.0, 0.0, 0.0], [np.inf, np.nan, 0.0], np.full((3, 3), np.nan), None, converged=False),
]


def rclpy_class(ros_type: str):
    pkg, kind, name = ros_type.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def same(ours, theirs, path="msg") -> bool:
    """Field by field: a rosbags message against an rclpy one (NaN equals NaN); True once every field
    compared equal (an AssertionError names the first that did not)."""
    if hasattr(ours, "__dataclass_fields__"):
        for name in ours.__dataclass_fields__:
            if name != "__msgtype__":
                same(getattr(ours, name), getattr(theirs, name), f"{path}.{name}")
    elif isinstance(ours, (list, tuple)) and ours and hasattr(ours[0], "__dataclass_fields__"):
        assert len(ours) == len(theirs), path
        for i, (a, b) in enumerate(zip(ours, theirs)):
            same(a, b, f"{path}[{i}]")
    elif isinstance(ours, np.ndarray) or isinstance(theirs, (np.ndarray, list, tuple)):
        a, b = np.asarray(ours), np.asarray(list(theirs) if not isinstance(theirs, np.ndarray) else theirs)
        assert a.shape == b.shape, path
        if a.dtype.kind == "f":
            assert np.array_equal(a, b, equal_nan=True), path
        else:
            assert (a == b).all(), path
    elif isinstance(ours, float):
        # float32 fields (a marker's colour) hold the float64 we meant rounded to float32
        assert (math.isnan(ours) and math.isnan(theirs)) or ours == theirs or np.float32(ours) == np.float32(theirs), \
            (path, ours, theirs)
    elif isinstance(theirs, bytes) and len(theirs) == 1:     # a `byte` field: rclpy gives bytes, rosbags an int
        assert ours == theirs[0], (path, ours, theirs)
    else:
        assert ours == theirs, (path, ours, theirs)
    return True


def published(ts):
    """(type, message) of every stock type the node publishes, representative and edge values."""
    out = []
    for frame in ("base_link", "", LONG_FRAME):
        for est in ESTIMATES:
            out.append(("geometry_msgs/msg/PoseWithCovarianceStamped", M.contact(ts, est, 1.7e9 + 0.123456789, frame)))
            out += [("visualization_msgs/msg/Marker", m) for m in M.contact_markers(ts, est, 1.7e9, frame)]
        out.append(("sensor_msgs/msg/Imu", M.imu(ts, 1.7e9, [0.1, -2.0, 1e-9], [0.0, 9.81, -1e3], frame)))
        out.append(("sensor_msgs/msg/Imu", M.imu(ts, 0.0, [np.nan, np.inf, -np.inf], [0, 0, 0], frame)))
        out.append(("geometry_msgs/msg/PoseStamped", M.tcp_pose(ts, [0.3, 0.0, 0.5], [0, 0, 0, 1], 1.7e9, frame)))
        out.append(("geometry_msgs/msg/WrenchStamped", M.wrench(ts, [1.5, -2.0, 30.0], [0.1, 0.0, -0.2], 1.7e9, frame)))
        out.append(("geometry_msgs/msg/WrenchStamped", M.wrench(ts, [0.0, 0.0, 0.0], None, 1.7e9, frame)))
    out.append(("diagnostic_msgs/msg/DiagnosticArray", M.diagnostics(ts, 1.7e9, [])))
    out.append(("diagnostic_msgs/msg/DiagnosticArray", M.diagnostics(
        ts, 1.7e9, [("tecdard/sim: faults", M.ERROR, "", {"": "", "robot_stale": "é" * 300}),
                    ("", M.OK, LONG_FRAME, {})])))
    return out


def test_rclpy_reads_every_stock_message_we_publish_as_we_meant_it(ts):
    for ros_type, msg in published(ts):
        ours = ts.encode(msg, ros_type)
        theirs = serialization.deserialize_message(ours, rclpy_class(ros_type))
        assert same(msg, theirs, ros_type)


def test_we_read_rclpys_own_bytes_of_every_stock_type(ts):
    """rclpy serialises (its padding bytes unset, some trailing bytes): we decode the same message."""
    for ros_type, msg in published(ts):
        theirs = serialization.deserialize_message(ts.encode(msg, ros_type), rclpy_class(ros_type))
        back = ts.decode(serialization.serialize_message(theirs), ros_type)
        assert same(back, theirs, ros_type)


def test_the_trigger_service_reply_and_a_joint_state_both_ways(ts):
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    for reply in ({"ok": True}, {"ok": False, "error": {"code": "fault", "message": "robot_stale: " + "x" * 999}}):
        msg = M.trigger_response(ts, reply)
        theirs = serialization.deserialize_message(ts.encode(msg, TRIGGER + "_Response"), Trigger.Response)
        assert theirs.success is reply["ok"] and theirs.message == msg.message
    js = JointState(name=["a", "", "panda_joint7"], position=[0.1, math.nan, -3.0], velocity=[], effort=[1.0, 2.0, 3.0])
    js.header.frame_id = LONG_FRAME
    back = ts.decode(serialization.serialize_message(js), "sensor_msgs/msg/JointState")
    assert same(back, js, "JointState")


def test_the_tf_message_reads_back_and_is_a_sequence_of_rclpys_transforms(ts):
    """No ros-tf2-msgs wheel: TFMessage is a sequence of geometry_msgs/TransformStamped, which rclpy
    has. Our TFMessage's one element, serialised alone by us, is what rclpy reads as that transform."""
    from geometry_msgs.msg import TransformStamped
    msg = M.contact_tf(ts, ESTIMATES[0], 1.7e9, "base_link", "sim/contact")
    raw = ts.encode(msg, "tf2_msgs/msg/TFMessage")
    assert int.from_bytes(raw[4:8], "little") == 1
    one = serialization.deserialize_message(ts.encode(msg.transforms[0], "geometry_msgs/msg/TransformStamped"),
                                            TransformStamped)
    assert same(ts.decode(raw, "tf2_msgs/msg/TFMessage").transforms[0], one, "transform")
    assert one.child_frame_id == "sim/contact" and not one.child_frame_id.startswith("/")


# -- type hashes ---------------------------------------------------------------------------------
def typesupport_hash(cls) -> str:
    """The RIHS01 hash the generated C type support of an rclpy message or service class reports."""
    cls.__class__.__import_type_support__()
    cap = cls.__class__._TYPE_SUPPORT
    name_of = ctypes.pythonapi.PyCapsule_GetName
    name_of.restype, name_of.argtypes = ctypes.c_char_p, [ctypes.py_object]
    pointer = ctypes.pythonapi.PyCapsule_GetPointer
    pointer.restype, pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    ptr = pointer(cap, name_of(cap))

    class Hash(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint8), ("value", ctypes.c_uint8 * 32)]
    # rosidl_message_type_support_t: identifier, data, func, get_type_hash_func; a service's has request,
    # response and event type supports and the event's two handle functions before its get_type_hash_func
    slot = 8 if hasattr(cls, "Request") else 3
    fn = ctypes.cast(ptr + slot * ctypes.sizeof(ctypes.c_void_p), ctypes.POINTER(ctypes.c_void_p)).contents.value
    h = ctypes.CFUNCTYPE(ctypes.POINTER(Hash), ctypes.c_void_p)(fn)(ptr).contents
    return f"RIHS0{h.version}_{bytes(h.value).hex()}"


def wheel_hash(ros_type: str) -> str:
    pkg, kind, name = ros_type.split("/")
    data = json.loads((SHARE / pkg / kind / f"{name}.json").read_text())
    return next(h["hash_string"] for h in data["type_hashes"] if h["type_name"] == ros_type)


PARAMETER_SERVICES = sorted(__import__("tecdard.ros2.parameters", fromlist=["SERVICES"]).SERVICES.values())


@pytest.mark.parametrize("ros_type", STOCK + ["sensor_msgs/msg/JointState", TRIGGER, *PARAMETER_SERVICES,
                                              "rcl_interfaces/msg/ParameterEvent",
                                              "type_description_interfaces/srv/GetTypeDescription"])
def test_our_hash_of_each_stock_type_is_rosidls(ts, ros_type):
    ours = ts.type_hash(ros_type)
    assert ours == wheel_hash(ros_type)
    assert ours == typesupport_hash(rclpy_class(ros_type))


def rosidl_generate(tmp: pathlib.Path, package: str, files: dict[str, str], deps: list[str]) -> dict[str, str]:
    """rosidl's own pipeline on .msg/.srv texts: rosidl_adapter to IDL, rosidl_generator_type_description
    to hashes (type name -> RIHS01), dependencies from the wheels' JSON type descriptions."""
    from rosidl_adapter.action import convert_action_to_idl
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_adapter.srv import convert_srv_to_idl
    from rosidl_generator_type_description import generate_type_hash
    src, idl, out = tmp / "src" / package, tmp / "idl", tmp / "out"
    tuples = []
    for rel, text in files.items():
        path = src / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        convert = {".msg": convert_msg_to_idl, ".srv": convert_srv_to_idl,
                   ".action": convert_action_to_idl}[pathlib.Path(rel).suffix]
        target = idl / pathlib.Path(rel).parent
        target.mkdir(parents=True, exist_ok=True)
        convert(src, package, pathlib.Path(rel), target)
        tuples.append(f"{idl}:{pathlib.Path(rel).with_suffix('.idl')}")
    args = tmp / "args.json"
    args.write_text(json.dumps({"package_name": package, "output_dir": str(out), "idl_tuples": tuples,
                                "include_paths": [f"{d}:{SHARE / d}" for d in deps]}))
    hashes = {}
    for generated in generate_type_hash(str(args)):
        for h in json.loads(pathlib.Path(generated).read_text())["type_hashes"]:
            hashes[h["type_name"]] = h["hash_string"]
    return hashes


@pytest.mark.slow
def test_our_hashes_of_tecdar_msgs_are_what_rosidls_generator_makes_of_the_package(ts, tmp_path, capsys):
    files = {str(p.relative_to(MSGS_DIR)): p.read_text() for p in sorted(MSGS_DIR.glob("*/*.*")) if p.suffix in
             (".msg", ".srv", ".action")}
    theirs = rosidl_generate(tmp_path, "tecdar_msgs", files,
                             ["action_msgs", "builtin_interfaces", "geometry_msgs", "service_msgs", "std_msgs",
                              "unique_identifier_msgs"])
    capsys.readouterr()
    mine = {name: h for name, h in theirs.items() if name.startswith("tecdar_msgs/")}
    n_srv = len(list((MSGS_DIR / "srv").glob("*.srv")))
    n_action = len(list((MSGS_DIR / "action").glob("*.action")))
    assert n_srv == len(task_verbs.names()) + 2      # each task verb, cancel and status
    assert n_action == len(task_verbs.names())       # each task verb
    # Event; each service, its request, response and event; each action, its goal, result, feedback, feedback
    # message, and its two services with their request, response and event
    assert len(mine) == 1 + 4 * n_srv + 13 * n_action
    for name, h in mine.items():
        assert ts.type_hash(name) == h, name


def test_each_action_s_goal_is_its_service_s_request():
    """The task verbs as actions take the same fields as their services (one intake, one validation)."""
    for path in sorted((MSGS_DIR / "action").glob("*.action")):
        goal = path.read_text().split("\n---\n")[0]
        request = (MSGS_DIR / "srv" / f"{path.stem}.srv").read_text().split("\n---\n")[0]
        assert goal.strip() == request.strip(), path.name


def test_our_cancel_goal_hash_is_action_msgs_own(ts):
    from tecdard.ros2.typesupport import CANCEL_GOAL, CANCEL_GOAL_SRV
    ts.add_service(CANCEL_GOAL_SRV, CANCEL_GOAL)
    shipped = json.loads((SHARE / "action_msgs" / "srv" / "CancelGoal.json").read_text())["type_hashes"]
    for entry in shipped:
        if entry["type_name"].startswith(CANCEL_GOAL):
            assert ts.type_hash(entry["type_name"]) == entry["hash_string"], entry["type_name"]


def test_our_tfmessage_hash_is_what_rosidl_makes_of_tf2_msgs_definition(ts, tmp_path, capsys):
    theirs = rosidl_generate(tmp_path, "tf2_msgs", {"msg/TFMessage.msg": TFMESSAGE_MSG},
                             ["builtin_interfaces", "geometry_msgs", "std_msgs"])
    capsys.readouterr()
    assert ts.type_hash("tf2_msgs/msg/TFMessage") == theirs["tf2_msgs/msg/TFMessage"]


def test_humble_says_type_hash_not_supported_in_keys_and_tokens():
    humble = TypeSupport("humble")
    assert humble.type_hash("sensor_msgs/msg/Imu") == HASH_NOT_SUPPORTED
    node = rmw.NodeInfo(0, "abc", 0, "/sim", "tecdard")
    token = rmw.entity_token(node, 3, rmw.PUBLISHER, "/sim/imu", dds_type_name("sensor_msgs/msg/Imu"),
                             humble.type_hash("sensor_msgs/msg/Imu"), rmw.SENSOR_DATA)
    assert rmw.parse_token(token).type_hash == HASH_NOT_SUPPORTED
    assert rmw.data_keyexpr(0, "/sim/imu", "sensor_msgs::msg::dds_::Imu_", HASH_NOT_SUPPORTED) == \
        "0/sim/imu/sensor_msgs::msg::dds_::Imu_/TypeHashNotSupported"


# The hashes Jazzy systems report for stock types the node publishes or subscribes, read off Jazzy installations
# by others: `ros2 topic info -v /tf` on a Jazzy node and a Jazzy bag's metadata.yaml (TFMessage), the constants
# of a firmware written against Jazzy's rmw_zenoh_cpp (Imu, its key and its token below), rmw_zenoh's design
# document (String), a Jazzy client library's messages (DiagnosticArray, Marker), and `ros2 topic info -v
# /joint_states` on a ros2_control system (JointState). None of them comes from the wheels the other tests use.
JAZZY_HASHES = {
    "sensor_msgs/msg/Imu": "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "diagnostic_msgs/msg/DiagnosticArray": "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
    "visualization_msgs/msg/Marker": "RIHS01_45b13ccf791f225962bf74e746f9644518855d783a6f42ba0cc14fde2b4f3ce0",
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
}
JAZZY_ZID = "100f0e0d0c0b0a090807060504030201"
JAZZY_IMU_KEY = ("0/nucleo/imu/data/sensor_msgs::msg::dds_::Imu_/"
                 "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b")
JAZZY_IMU_TOKEN = (f"@ros2_lv/0/{JAZZY_ZID}/0/11/MP/%/%/nucleo_h743zi2/%nucleo%imu%data/sensor_msgs::msg::dds_::Imu_/"
                   "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b/::,:,:,:,,")


def test_with_distro_jazzy_the_hashes_keys_and_tokens_are_what_jazzy_systems_report():
    """`ros2.distro: jazzy`: every hash, key and token as a Jazzy system of rmw_zenoh_cpp writes it. Jazzy and
    Kilted define these types alike, so the Kilted store gives the same; this holds it against Jazzy's own."""
    jazzy = TypeSupport("jazzy")
    for name, h in JAZZY_HASHES.items():
        assert jazzy.type_hash(name) == h, name
    node = rmw.NodeInfo(0, JAZZY_ZID, 0, "", "nucleo_h743zi2")
    assert node.token() == f"@ros2_lv/0/{JAZZY_ZID}/0/0/NN/%/%/nucleo_h743zi2"
    imu = jazzy.type_hash("sensor_msgs/msg/Imu")
    assert rmw.data_keyexpr(0, "/nucleo/imu/data", dds_type_name("sensor_msgs/msg/Imu"), imu) == JAZZY_IMU_KEY
    assert rmw.entity_token(node, 11, rmw.PUBLISHER, "/nucleo/imu/data", dds_type_name("sensor_msgs/msg/Imu"), imu,
                            rmw.DEFAULT_QOS) == JAZZY_IMU_TOKEN
    assert rmw.parse_token(JAZZY_IMU_TOKEN).qos == rmw.DEFAULT_QOS


# -- rmw_zenoh's conventions -----------------------------------------------------------------------
def test_data_keys_are_the_design_documents():
    """design.md's own examples: chatter in the default domain, and under the /robot1 namespace."""
    chatter = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    assert rmw.data_keyexpr(0, "/chatter", "std_msgs::msg::dds_::String_", chatter) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{chatter}"
    assert rmw.data_keyexpr(0, rmw.fully_qualified("/robot1", "chatter"), "std_msgs::msg::dds_::String_", chatter) \
        == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{chatter}"
    assert dds_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_"
    assert rmw.fully_qualified("/sim", "/diagnostics") == "/diagnostics"


def test_tokens_read_back_field_by_field_as_the_design_documents_examples():
    listener = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    node = rmw.NodeInfo(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "", "listener")
    assert node.token() == listener
    h = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    sub = rmw.entity_token(node, 10, rmw.SUBSCRIPTION, "/chatter", "std_msgs::msg::dds_::String_", h, rmw.Qos(depth=10))
    assert sub == ("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
                   f"std_msgs::msg::dds_::String_/{h}/::,10:,:,:,,")
    t = rmw.parse_token(sub)
    assert (t.domain_id, t.session_id, t.node_id, t.entity_id, t.kind, t.enclave, t.namespace, t.node_name, t.name,
            t.dds_type, t.type_hash, t.qos) == (2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, "MS", "", "", "listener",
                                                "/chatter", "std_msgs::msg::dds_::String_", h, rmw.Qos(depth=10))
    ns = rmw.parse_token(rmw.NodeInfo(0, "z", 0, "/lab/arm1", "tecdard").token())
    assert ns.namespace == "/lab/arm1" and ns.kind == "NN"
    for bad in ("@ros2_lv/0/z/0/0/NN/%/%", "ros2_lv/0/z/0/0/NN/%/%/n", "@ros2_lv/0/z/0/1/MP/%/%/n"):
        with pytest.raises(ValueError):
            rmw.parse_token(bad)


def test_qos_strings_are_rmw_zenohs_and_the_sdk_reads_them_alike():
    from zenoh_ros2_sdk.qos import QosDurability, QosHistoryKind, QosProfile, QosReliability
    assert rmw.qos_keyexpr(rmw.SENSOR_DATA) == "2::,5:,:,:,,"
    assert rmw.qos_keyexpr(rmw.RELIABLE_10) == "::,10:,:,:,,"
    assert rmw.qos_keyexpr(rmw.TF_QOS) == "::,100:,:,:,,"
    assert rmw.qos_keyexpr(rmw.DEFAULT_QOS) == "::,:,:,:,,"
    for qos in (rmw.SENSOR_DATA, rmw.RELIABLE_10, rmw.TF_QOS, rmw.Qos(durability=rmw.TRANSIENT_LOCAL, depth=1)):
        text = rmw.qos_keyexpr(qos)
        assert rmw.parse_qos(text) == qos
        theirs = QosProfile.decode(text)
        assert theirs.reliability == (QosReliability.BEST_EFFORT if qos.reliability == rmw.BEST_EFFORT
                                      else QosReliability.RELIABLE)
        assert theirs.durability == (QosDurability.TRANSIENT_LOCAL if qos.durability == rmw.TRANSIENT_LOCAL
                                     else QosDurability.VOLATILE)
        assert theirs.history_kind == QosHistoryKind.KEEP_LAST and theirs.history_depth == qos.depth


def test_the_attachment_is_33_bytes_little_endian_and_the_sdk_reads_it():
    from zenoh_ros2_sdk.attachment import Attachment
    gid = rmw.gid("@ros2_lv/0/z/0/1/MP/%/%/n/%t/x/y/::,:,:,:,,")
    raw = rmw.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(raw) == rmw.ATTACHMENT_BYTES == 33
    assert raw[:8] == (7).to_bytes(8, "little") and raw[8:16] == (1_700_000_000_123_456_789).to_bytes(8, "little")
    assert raw[16] == 16 and raw[17:] == gid
    assert rmw.parse_attachment(raw) == (7, 1_700_000_000_123_456_789, gid)
    theirs = Attachment.from_bytes(raw)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (7, 1_700_000_000_123_456_789, gid)
    assert rmw.parse_attachment(Attachment(3, 5, gid).to_bytes()) == (3, 5, gid)
    for bad in (b"", raw[:-1], raw[:16] + b"\x08" + raw[17:]):
        with pytest.raises(ValueError):
            rmw.parse_attachment(bad)


def test_gids_differ_per_entity_and_are_16_bytes():
    a, b = rmw.gid("@ros2_lv/0/z/0/1/MP/x"), rmw.gid("@ros2_lv/0/z/0/2/MP/x")
    assert len(a) == len(b) == 16 and a != b


# -- requests ----------------------------------------------------------------------------------------
ROS_KIND = {"number": ("float64",), "direction": ("float64[]",), "numbers": ("float64[]",), "choice": ("string",),
            "bool": ("uint8",), "int_choice": ("uint8",), "grid": ("int32[]",)}


def srv_request_fields(verb: str) -> dict[str, str]:
    text = (MSGS_DIR / "srv" / f"{verb.capitalize()}.srv").read_text().split("\n---\n")[0]
    fields = {}
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if line and "=" not in line:
            typ, name = line.split()
            fields[name] = typ
    return fields


@pytest.mark.parametrize("verb", task_verbs.names())
def test_every_task_verb_has_its_service_with_every_field_and_nothing_else(verb):
    spec = task_verbs.get(verb)
    fields = srv_request_fields(verb)
    assert set(fields) == {f.name for f in spec.fields}
    for f in spec.fields:
        assert fields[f.name] in ROS_KIND[f.kind], (verb, f.name)


def test_a_ros_request_is_validated_as_the_zenoh_command_is(ts):
    limits = C.Limits()
    rotate = ts.cls("tecdar_msgs/srv/Rotate_Request")
    spec = task_verbs.get("rotate")

    def admit(**kw):
        base = dict(angle_deg=math.nan, speed=math.nan, probe_distance=math.nan, direction=np.zeros(0),
                    strategy="", turn_tool=M.FLAG_DEFAULT)
        payload = M.request_payload(spec.fields, rotate(**{**base, **kw}))
        return C.admit("rotate", json.dumps(payload), limits)
    assert admit(angle_deg=30.0) == C.admit("rotate", '{"angle_deg": 30}', limits)
    assert admit(angle_deg=30.0, turn_tool=M.FLAG_FALSE)["turn_tool"] is False
    cases = {"missing_field": dict(), "out_of_limits": dict(angle_deg=500.0),
             "bad_type": dict(angle_deg=math.inf)}
    for code, kw in cases.items():
        with pytest.raises(C.CommandError) as exc:
            admit(**kw)
        assert exc.value.code == code and "angle_deg" in exc.value.message
    for code, kw in {"bad_type": dict(angle_deg=10.0, direction=np.array([1.0, 0.0])),
                     "out_of_limits": dict(angle_deg=10.0, direction=np.array([2.0, 0.0, 0.0])),
                     "bad_type ": dict(angle_deg=10.0, strategy="sideways"),
                     "bad_type  ": dict(angle_deg=10.0, turn_tool=7)}.items():
        with pytest.raises(C.CommandError) as exc:
            admit(**kw)
        assert exc.value.code == code.strip()


def test_the_imu_is_averaged_over_blocks_on_an_absolute_grid():
    odr, rate = 6667.0, 1000.0
    avg = _BlockAverage(rate)
    t = np.arange(0, 2000) / odr + 100.0
    b = np.column_stack([t, np.sin(t)[:, None] * [1, 2, 3], np.ones((len(t), 3)) * 9.81])
    blocks = []
    for chunk in np.array_split(b, 37):          # delivered in batches of any size
        blocks += avg.add(chunk)
    times = np.array([x[0] for x in blocks])
    assert abs(len(blocks) - (t[-1] - t[0]) * rate) <= 2
    assert np.all(np.diff(times) > 0.5 / rate) and np.all(np.diff(times) < 1.5 / rate)
    first = b[np.floor(b[:, 0] * rate) == np.floor(b[0, 0] * rate)]
    assert np.allclose(blocks[0][1], first[:, 1:4].mean(axis=0)) and np.allclose(blocks[0][2], 9.81)


def test_a_line_contacts_orientation_has_its_axis_as_x():
    from tecdard.control.geometry import quat_to_matrix
    for axis in ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.3, -0.2, 0.9]):
        R = quat_to_matrix(np.array(M.axis_quat(axis)))
        assert np.allclose(R[:, 0], np.array(axis) / np.linalg.norm(axis))
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert M.axis_quat(None) == M.axis_quat([0.0, 0.0, 0.0]) == (0.0, 0.0, 0.0, 1.0)


def test_rclpy_reads_our_parameter_replies_and_we_read_its_requests(ts):
    """Issue 51 item 1: the parameter services' responses, as rclpy deserialises them, say what the config says:
    the value and type of a float option, a table as its JSON, a descriptor read-only with the option's range; a
    set refused with the reason; and rclpy's own requests decode on our side."""
    import yaml
    from rcl_interfaces.srv import DescribeParameters, GetParameters, GetParameterTypes, ListParameters, SetParameters
    from rclpy import serialization
    from tecdard.ros2 import parameters as P
    from tests.conftest import SIM_CONFIG
    from tecdard.runtime.option_sections import sections
    params = P.ParameterSet(yaml.safe_load(SIM_CONFIG.read_text()), sections())

    def round_trip(cls, srv_type: str, request):
        req = ts.decode(serialization.serialize_message(request), srv_type + "_Request")
        return serialization.deserialize_message(ts.encode(P.respond(ts, params, srv_type, req),
                                                           srv_type + "_Response"), cls.Response)
    got = round_trip(GetParameters, "rcl_interfaces/srv/GetParameters",
                     GetParameters.Request(names=["control.max_force_n", "estimator.eta_table", "robot.name", "no.such"]))
    assert [v.type for v in got.values] == [P.DOUBLE, P.STRING, P.STRING, P.NOT_SET]
    assert got.values[0].double_value == 15.0 and got.values[2].string_value == "sim"
    assert json.loads(got.values[1].string_value) == [[30.0, 2.0]]
    types = round_trip(GetParameterTypes, "rcl_interfaces/srv/GetParameterTypes",
                       GetParameterTypes.Request(names=["control.max_force_n", "robot.q_home"]))
    assert list(types.types) == [P.DOUBLE, P.DOUBLE_ARRAY]
    desc = round_trip(DescribeParameters, "rcl_interfaces/srv/DescribeParameters",
                      DescribeParameters.Request(names=["control.max_force_n"])).descriptors[0]
    assert desc.read_only and desc.type == P.DOUBLE and "N" in desc.description
    assert (desc.floating_point_range[0].from_value, desc.floating_point_range[0].to_value) == (0.0, 200.0)
    listed = round_trip(ListParameters, "rcl_interfaces/srv/ListParameters", ListParameters.Request())
    assert "control.max_force_n" in listed.result.names and "control" in listed.result.prefixes
    assert len(listed.result.names) == len(params.params) > 100
    only = round_trip(ListParameters, "rcl_interfaces/srv/ListParameters", ListParameters.Request(prefixes=["limits"]))
    assert only.result.names and all(n.startswith("limits.") for n in only.result.names)
    from rcl_interfaces.msg import Parameter, ParameterValue
    refused = round_trip(SetParameters, "rcl_interfaces/srv/SetParameters", SetParameters.Request(
        parameters=[Parameter(name="control.max_force_n", value=ParameterValue(type=3, double_value=99.0))]))
    assert [r.successful for r in refused.results] == [False] and "restart" in refused.results[0].reason
