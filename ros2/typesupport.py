"""ROS 2 message types for the node: CDR encoding, DDS type names and RIHS01 type hashes, from rosbags.

rosbags (a typestore with CDR serialisation and REP 2016 hashing) holds the stock types. The
`tecdar_msgs` types are registered from the ament package's own .msg and .srv files beside this
module, never written a second time here. Two things rosbags does not do are done here, on top of
its typestore:
- a service's type description (REP 2011): the service type with its request, response and event
  messages, the event holding `service_msgs/ServiceEventInfo` and a request and a response
  sequence of at most one each, as rosidl generates it;
- `service_msgs/ServiceEventInfo.client_gid`: rosbags keeps the .msg's `char[16]`, which rosidl
  hashes as `uint8[16]` (`char` is uint8 in .msg). Bytes on the wire are the same either way.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass

MSGS_DIR = pathlib.Path(__file__).parent / "tecdar_msgs"
PACKAGE = "tecdar_msgs"
DISTROS = ("jazzy", "kilted", "rolling", "humble")
HASH_NOT_SUPPORTED = "TypeHashNotSupported"       # what Humble's rmw_zenoh puts where the hash goes
SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
ENCAPSULATION_BYTES = 4                            # CDR's header: representation id and options
# bytes a decoded message may be followed by: rclpy's serialiser leaves 8 (its buffer's tail), alignment
# padding up to 7; anything longer is not the message it says it is
MAX_TRAILING_BYTES = 16


class TypeError_(ValueError):
    """A type or a payload the node cannot encode or decode (one line)."""


@dataclass(frozen=True)
class ServiceType:
    name: str            # pkg/srv/Name
    request: str         # pkg/srv/Name_Request
    response: str        # pkg/srv/Name_Response


@dataclass(frozen=True)
class ActionType:
    """An action's types as rosidl names them (pkg/action/Name_...): its goal, result and feedback, its two
    services (SendGoal, GetResult: ServiceType) and its feedback message."""
    name: str
    goal: str
    result: str
    feedback: str
    send_goal: ServiceType
    get_result: ServiceType
    feedback_message: str


UUID = "unique_identifier_msgs/msg/UUID"
TIME = "builtin_interfaces/msg/Time"
CANCEL_GOAL = "action_msgs/srv/CancelGoal"
# action_msgs/srv/CancelGoal as action_msgs ships it (its comments left out: they are not hashed)
CANCEL_GOAL_SRV = ("action_msgs/GoalInfo goal_info\n---\nint8 ERROR_NONE=0\nint8 ERROR_REJECTED=1\n"
                   "int8 ERROR_UNKNOWN_GOAL_ID=2\nint8 ERROR_GOAL_TERMINATED=3\nint8 return_code\n"
                   "action_msgs/GoalInfo[] goals_canceling\n")


def dds_type_name(ros_type: str) -> str:
    """`sensor_msgs/msg/Imu` -> `sensor_msgs::msg::dds_::Imu_` (services: `pkg::srv::dds_::Name_`)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def split_srv(text: str, name: str, parts: int = 2) -> tuple[str, ...]:
    """A .srv file's request and response parts (around its `---` line); an .action's goal, result and
    feedback (`parts` 3)."""
    lines = text.splitlines()
    cut = [i for i, line in enumerate(lines) if line.strip() == "---"]
    if len(cut) != parts - 1:
        kind = ".srv" if parts == 2 else ".action"
        raise TypeError_(f"{name}: a {kind} needs exactly {parts - 1} '---' line(s), found {len(cut)}")
    bounds = [-1] + cut + [len(lines)]
    return tuple("\n".join(lines[a + 1:b]) for a, b in zip(bounds, bounds[1:]))


class TypeSupport:
    """The typestore the node encodes with: the stock types of rosbags' Kilted store (their
    definitions are the same in Jazzy and Rolling, and in Humble for every type used here) and
    `tecdar_msgs`. `distro` picks the type hash: RIHS01 or Humble's TypeHashNotSupported."""

    def __init__(self, distro: str = "kilted", msgs_dir: pathlib.Path = MSGS_DIR):
        from rosbags.typesys import Stores, get_typestore
        if distro not in DISTROS:
            raise TypeError_(f"distro: {distro!r} is not one of {', '.join(DISTROS)}")
        self.distro = distro
        self.store = get_typestore(Stores.ROS2_KILTED)
        self._fix_service_event_info()
        self.services: dict[str, ServiceType] = {}
        self.actions: dict[str, ActionType] = {}
        self._hashes: dict[str, str] = {}
        self._register_package(msgs_dir)

    # -- building -----------------------------------------------------------------------------
    def _fix_service_event_info(self) -> None:
        from rosbags.typesys.base import Nodetype
        consts, fields = self.store.fielddefs[SERVICE_EVENT_INFO]
        fixed = [(n, (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), 16)) if n == "client_gid" else d)
                 for n, d in fields]
        self.store.fielddefs[SERVICE_EVENT_INFO] = (consts, fixed)

    def _register_package(self, root: pathlib.Path) -> None:
        from rosbags.typesys import get_types_from_msg
        types: dict = {}
        for path in sorted((root / "msg").glob("*.msg")):
            types.update(get_types_from_msg(path.read_text(), f"{PACKAGE}/msg/{path.stem}"))
        for path in sorted((root / "srv").glob("*.srv")):
            types.update(self._service_types(path.read_text(), f"{PACKAGE}/srv/{path.stem}"))
        if not types:
            raise TypeError_(f"{root}: no .msg or .srv files (the tecdar_msgs package is missing)")
        for path in sorted((root / "action").glob("*.action")):
            types.update(self._action_types(path.read_text(), f"{PACKAGE}/action/{path.stem}"))
        self.store.register(types)

    def _action_types(self, text: str, name: str) -> dict:
        """An .action's types as rosidl generates them: Name_Goal, _Result, _Feedback; the services
        Name_SendGoal (goal_id and goal; accepted and stamp) and Name_GetResult (goal_id; status and result),
        each with its event; Name_FeedbackMessage (goal_id and feedback); and Name, whose fields name them."""
        from rosbags.typesys import get_types_from_msg
        from rosbags.typesys.base import Nodetype
        goal, result, feedback = split_srv(text, name, parts=3)
        types: dict = {}
        for part, body in (("_Goal", goal), ("_Result", result), ("_Feedback", feedback)):
            types.update({k.replace("/action/msg/", "/action/"): v for k, v in
                          get_types_from_msg(body, name + part).items()})
        uuid = ("goal_id", (Nodetype.NAME, UUID))
        send_goal = self._service_parts(name + "_SendGoal",
                                        [uuid, ("goal", (Nodetype.NAME, name + "_Goal"))],
                                        [("accepted", (Nodetype.BASE, ("bool", 0))), ("stamp", (Nodetype.NAME, TIME))],
                                        types)
        get_result = self._service_parts(name + "_GetResult", [uuid],
                                         [("status", (Nodetype.BASE, ("int8", 0))),
                                          ("result", (Nodetype.NAME, name + "_Result"))], types)
        fb_message = name + "_FeedbackMessage"
        types[fb_message] = ([], [uuid, ("feedback", (Nodetype.NAME, name + "_Feedback"))])
        types[name] = ([], [("goal", (Nodetype.NAME, name + "_Goal")), ("result", (Nodetype.NAME, name + "_Result")),
                            ("feedback", (Nodetype.NAME, name + "_Feedback")),
                            ("send_goal_service", (Nodetype.NAME, send_goal.name)),
                            ("get_result_service", (Nodetype.NAME, get_result.name)),
                            ("feedback_message", (Nodetype.NAME, fb_message))])
        self.actions[name] = ActionType(name, name + "_Goal", name + "_Result", name + "_Feedback", send_goal,
                                        get_result, fb_message)
        return types

    def _service_parts(self, name: str, request: list, response: list, types: dict) -> ServiceType:
        """A service made of field lists (an action's), with its event and service types, into `types`."""
        types[name + "_Request"], types[name + "_Response"] = ([], request), ([], response)
        return self._envelope(name, types)

    def _envelope(self, name: str, types: dict) -> ServiceType:
        """The event and service types of the service `name` whose request and response are in `types`, as
        rosidl generates them (the event: ServiceEventInfo, then at most one request and one response)."""
        from rosbags.typesys.base import Nodetype
        req, res, event = name + "_Request", name + "_Response", name + "_Event"
        types[event] = ([], [("info", (Nodetype.NAME, SERVICE_EVENT_INFO)),
                             ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, req), 1))),
                             ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, res), 1)))])
        types[name] = ([], [("request_message", (Nodetype.NAME, req)), ("response_message", (Nodetype.NAME, res)),
                            ("event_message", (Nodetype.NAME, event))])
        self.services[name] = ServiceType(name, req, res)
        return self.services[name]

    def _service_types(self, text: str, name: str) -> dict:
        """The request, response, event and service types of one .srv, named as rosidl names them."""
        from rosbags.typesys import get_types_from_msg
        request, response = split_srv(text, name)
        types: dict = {}
        for part, body in (("_Request", request), ("_Response", response)):
            # rosbags files a service's parts under pkg/srv/msg/; rosidl names them pkg/srv/Name_Request
            types.update({k.replace("/srv/msg/", "/srv/"): v for k, v in
                          get_types_from_msg(body, name + part).items()})
        self._envelope(name, types)
        return types

    def add_service(self, text: str, name: str) -> ServiceType:
        """A stock service from its .srv text (std_srvs/srv/Trigger)."""
        if name not in self.services:
            self.store.register(self._service_types(text, name))
        return self.services[name]

    # -- using ----------------------------------------------------------------------------------
    def type_hash(self, ros_type: str) -> str:
        """RIHS01_<sha256> of the type's description (REP 2016), or Humble's TypeHashNotSupported."""
        if self.distro == "humble":
            return HASH_NOT_SUPPORTED
        if ros_type not in self._hashes:
            self._hashes[ros_type] = self.store.hash_rihs01(ros_type)
        return self._hashes[ros_type]

    def rihs01(self, ros_type: str) -> str:
        """The RIHS01 hash whatever the distro (for tests and docs)."""
        return self.store.hash_rihs01(ros_type)

    def cls(self, ros_type: str):
        return self.store.types[ros_type]

    def encode(self, msg, ros_type: str) -> bytes:
        """CDR, little endian, with its 4-byte encapsulation header."""
        return bytes(self.store.serialize_cdr(msg, ros_type))

    def decode(self, raw: bytes, ros_type: str):
        """The message of CDR bytes; TypeError_ naming the type for anything that is not one."""
        if len(raw) < ENCAPSULATION_BYTES:
            raise TypeError_(f"{ros_type}: {len(raw)} bytes, not a CDR payload")
        if raw[0] != 0 or raw[1] not in (0, 1):
            raise TypeError_(f"{ros_type}: encapsulation {raw[:2].hex()} is not plain CDR (0000 or 0001)")
        msgdef = self.store.get_msgdef(ros_type)
        decode = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
        try:
            msg, end = decode(memoryview(raw)[ENCAPSULATION_BYTES:], 0, msgdef.cls, self.store)
        except Exception as exc:
            raise TypeError_(f"{ros_type}: {len(raw)} bytes that do not decode ({type(exc).__name__}: "
                             f"{str(exc)[:120]})") from None
        extra = len(raw) - ENCAPSULATION_BYTES - end
        if extra > MAX_TRAILING_BYTES:
            raise TypeError_(f"{ros_type}: {extra} bytes after the message's end (at most {MAX_TRAILING_BYTES})")
        return msg
