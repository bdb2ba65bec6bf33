"""The node's `~/get_type_description` (type_description_interfaces, REP 2016): the full description of every
type it uses, ours included, so that ROS 2's tools decode `tecdar_msgs` without a colcon build.

The description is the one the RIHS01 hash is taken over (rosbags' TypeStore.hash_rihs01 builds it the same
way and keeps only its digest): the type, then every type it refers to, sorted by name. Each field has its
type id, capacity and nested type name. `type_sources` carries the .msg or .srv text of `tecdar_msgs` types;
stock types are described but not sourced.
"""
from __future__ import annotations

import hashlib
import json

SERVICE = "type_description_interfaces/srv/GetTypeDescription"
SRV_TEXT = ("string type_name\nstring type_hash\nbool include_type_sources true\n---\nbool successful\n"
            "string failure_reason\ntype_description_interfaces/TypeDescription type_description\n"
            "type_description_interfaces/TypeSource[] type_sources\ntype_description_interfaces/KeyValue[] "
            "extra_information\n")
NOT_IN_USE = "Type not currently in use by this node"          # rclcpp's own words
HASH_MISMATCH = "Type hash does not match the type in use by this node"


def description(store, typ: str) -> dict:
    """{type_description, referenced_type_descriptions} of `typ` in rosbags' `store`, as REP 2016 hashes it."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys.store import TIDMAP
    structs: dict[str, dict] = {}

    def field(name: str, desc) -> dict:
        increment, capacity, string_capacity, subtype = 0, 0, 0, ""
        if desc[0] == Nodetype.ARRAY:
            increment, capacity = 48, desc[1][1]
            kind, rest = desc[1][0]
        elif desc[0] == Nodetype.SEQUENCE:
            count = desc[1][1]
            increment, capacity = (96, count) if count else (144, 0)
            kind, rest = desc[1][0]
        else:
            kind, rest = desc
        if kind == Nodetype.NAME:
            tid, subtype = increment + 1, rest
            struct(subtype)
        elif rest[0] == "string" and rest[1]:
            tid, string_capacity = increment + TIDMAP["bounded_string"], rest[1]
        else:
            tid = increment + TIDMAP[rest[0]]
        return {"name": name, "type": {"type_id": tid, "capacity": capacity, "string_capacity": string_capacity,
                                       "nested_type_name": subtype}}

    def struct(name: str) -> dict:
        if name not in structs:
            fields = store.fielddefs[name][1] or [("structure_needs_at_least_one_member", (Nodetype.BASE, ("uint8", 0)))]
            structs[name] = {"type_name": name, "fields": [field(n, d) for n, d in fields]}
        return structs[name]

    top = struct(typ)
    return {"type_description": top, "referenced_type_descriptions": [s for n, s in sorted(structs.items()) if n != typ]}


def rihs01(desc: dict) -> str:
    return "RIHS01_" + hashlib.sha256(json.dumps(desc).encode()).hexdigest()


def _individual(T, d: dict):
    return T["type_description_interfaces/msg/IndividualTypeDescription"](
        type_name=d["type_name"], fields=[T["type_description_interfaces/msg/Field"](
            name=f["name"], type=T["type_description_interfaces/msg/FieldType"](**f["type"]), default_value="")
            for f in d["fields"]])


def respond(ts, in_use: dict[str, str], sources: dict[str, tuple[str, str]], req):
    """The GetTypeDescription response to `req`: `in_use` type name -> its hash (the node's types); `sources` type
    name -> (encoding, text) for those it has the source of."""
    T = ts.store.types
    Resp = T[SERVICE + "_Response"]
    empty = T["type_description_interfaces/msg/TypeDescription"](
        type_description=T["type_description_interfaces/msg/IndividualTypeDescription"](type_name="", fields=[]),
        referenced_type_descriptions=[])
    name = str(req.type_name)
    if name not in in_use:
        return Resp(successful=False, failure_reason=NOT_IN_USE, type_description=empty, type_sources=[],
                    extra_information=[])
    if req.type_hash and str(req.type_hash) != in_use[name]:
        return Resp(successful=False, failure_reason=HASH_MISMATCH, type_description=empty, type_sources=[],
                    extra_information=[])
    desc = description(ts.store, name)
    msg = T["type_description_interfaces/msg/TypeDescription"](
        type_description=_individual(T, desc["type_description"]),
        referenced_type_descriptions=[_individual(T, d) for d in desc["referenced_type_descriptions"]])
    wanted = [name] + [d["type_name"] for d in desc["referenced_type_descriptions"]]
    type_sources = [T["type_description_interfaces/msg/TypeSource"](type_name=n, encoding=sources[n][0],
                                                                     raw_file_contents=sources[n][1])
                    for n in wanted if n in sources] if req.include_type_sources else []
    return Resp(successful=True, failure_reason="", type_description=msg, type_sources=type_sources,
                extra_information=[])
