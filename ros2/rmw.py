"""rmw_zenoh's wire conventions: key expressions, liveliness tokens, QoS strings, attachments and GIDs.

Followed: rmw_zenoh's `docs/design.md` at commit 99a6a2bd10b949052f4f12c5854825dc005e95a5 (ros2/rmw_zenoh,
rolling; the same conventions as Jazzy from 0.2.4 and Kilted), and `qos_to_keyexpr` in its
`liveliness_utils.cpp` for the QoS string, whose defaults are rmw_zenoh's (reliable, volatile, keep
last 42, infinite durations, automatic liveliness): a field equal to its default is left empty.
"""
from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
GID_BYTES = 16
ATTACHMENT = struct.Struct("<qqB16s")      # sequence number, source timestamp (ns since the epoch), GID length, GID
ATTACHMENT_BYTES = ATTACHMENT.size         # 33

# rmw's enums (rmw/types.h)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclass(frozen=True)
class Qos:
    """The QoS an entity declares (what its liveliness token says)."""
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10


DEFAULT_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 42)           # rmw_zenoh's own defaults (qos.cpp)
SENSOR_DATA = Qos(BEST_EFFORT, VOLATILE, KEEP_LAST, 5)         # rclcpp's SensorDataQoS
RELIABLE_10 = Qos(RELIABLE, VOLATILE, KEEP_LAST, 10)           # the default profile; services' too
TF_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 100)               # tf2_ros::DynamicBroadcasterQoS


def qos_keyexpr(qos: Qos) -> str:
    """`<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>`,
    each field empty where it equals rmw_zenoh's default (durations: infinite, as ours are)."""
    def field(value: int, default: int) -> str:
        return "" if value == default else str(value)
    d = DEFAULT_QOS
    return (f"{field(qos.reliability, d.reliability)}:{field(qos.durability, d.durability)}:"
            f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}:,:,:,,")


def parse_qos(text: str) -> Qos:
    """The QoS of a token's QoS string (empty fields: rmw_zenoh's defaults); ValueError otherwise."""
    parts = text.split(":")
    if len(parts) != 6:
        raise ValueError(f"QoS {text[:60]!r}: expected 6 fields separated by ':'")
    history = parts[2].split(",")
    if len(history) != 2:
        raise ValueError(f"QoS {text[:60]!r}: history must be <kind>,<depth>")
    d = DEFAULT_QOS

    def num(s: str, default: int) -> int:
        return default if s == "" else int(s)
    return Qos(num(parts[0], d.reliability), num(parts[1], d.durability), num(history[0], d.history),
               num(history[1], d.depth))


def mangle(name: str) -> str:
    """A name in a token: every '/' as '%', and '%' alone for an empty one."""
    return name.replace("/", "%") if name else "%"


def fully_qualified(namespace: str, name: str) -> str:
    """`/<namespace>/<name>` for a relative name, the name itself for an absolute one."""
    if name.startswith("/"):
        return name
    ns = namespace.rstrip("/")
    return f"{ns}/{name}"


def data_keyexpr(domain_id: int, fq_name: str, dds_type: str, type_hash: str) -> str:
    """`<domain_id>/<fully qualified name without the leading slash>/<type name>/<type hash>`."""
    return f"{domain_id}/{fq_name.lstrip('/')}/{dds_type}/{type_hash}"


@dataclass(frozen=True)
class NodeInfo:
    domain_id: int
    session_id: str          # the Zenoh session's id, as zenoh prints it
    node_id: int
    namespace: str           # "/robot" or "" for none
    name: str
    enclave: str = ""

    def token(self) -> str:
        """`@ros2_lv/<domain>/<session>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>`."""
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.session_id}/{self.node_id}/{self.node_id}/{NODE}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}")


def entity_token(node: NodeInfo, entity_id: int, kind: str, fq_name: str, dds_type: str, type_hash: str,
                 qos: Qos) -> str:
    """A publisher's, subscription's, service server's or client's liveliness token."""
    return (f"{ADMIN_SPACE}/{node.domain_id}/{node.session_id}/{node.node_id}/{entity_id}/{kind}/"
            f"{mangle(node.enclave)}/{mangle(node.namespace)}/{node.name}/{mangle(fq_name)}/{dds_type}/"
            f"{mangle(type_hash)}/{qos_keyexpr(qos)}")


@dataclass(frozen=True)
class Token:
    """A liveliness token read back, field by field."""
    domain_id: int
    session_id: str
    node_id: int
    entity_id: int
    kind: str
    enclave: str
    namespace: str
    node_name: str
    name: str = ""
    dds_type: str = ""
    type_hash: str = ""
    qos: Qos | None = None


def parse_token(key: str) -> Token:
    """The fields of an `@ros2_lv/...` token (names unmangled); ValueError naming what is wrong."""
    parts = key.split("/")
    if not parts or parts[0] != ADMIN_SPACE:
        raise ValueError(f"{key[:80]!r}: not under {ADMIN_SPACE}")
    if len(parts) not in (9, 13):
        raise ValueError(f"{key[:80]!r}: {len(parts)} chunks, a node's token has 9 and an entity's 13")
    kind = parts[5]
    if kind not in ENTITY_KINDS or (kind == NODE) != (len(parts) == 9):
        raise ValueError(f"{key[:80]!r}: entity kind {kind!r} does not fit {len(parts)} chunks")

    def unmangle(s: str) -> str:
        return "" if s == "%" else s.replace("%", "/")
    base = dict(domain_id=int(parts[1]), session_id=parts[2], node_id=int(parts[3]), entity_id=int(parts[4]),
                kind=kind, enclave=unmangle(parts[6]), namespace=unmangle(parts[7]), node_name=parts[8])
    if kind == NODE:
        return Token(**base)
    return Token(**base, name=unmangle(parts[9]), dds_type=parts[10], type_hash=parts[11], qos=parse_qos(parts[12]))


def gid(token: str) -> bytes:
    """An entity's 16-byte GID, from its liveliness token (rmw_zenoh hashes the token too, with XXH3;
    peers take the GID as opaque bytes)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_BYTES).digest()


def attachment(seq: int, t_ns: int, gid_bytes: bytes) -> bytes:
    """The 33-byte attachment of every sample, query and reply."""
    return ATTACHMENT.pack(seq, t_ns, GID_BYTES, gid_bytes)


def parse_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an attachment; ValueError if it is not one."""
    if raw is None or len(raw) != ATTACHMENT_BYTES:
        raise ValueError(f"attachment: {0 if raw is None else len(raw)} bytes, expected {ATTACHMENT_BYTES}")
    seq, t_ns, n, g = ATTACHMENT.unpack(raw)
    if n != GID_BYTES:
        raise ValueError(f"attachment: GID length {n}, expected {GID_BYTES}")
    return seq, t_ns, g
