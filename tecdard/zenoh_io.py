"""Zenoh session configuration and the `tecdar/1` key expressions."""
from __future__ import annotations

import json

import zenoh

JSON = zenoh.Encoding.APPLICATION_JSON
# The daemon's transport drops any message larger than this before it reaches Python (Zenoh's own
# default is 1 GiB); commands are refused with a reply above tecdard.commands.MAX_PAYLOAD_BYTES.
DAEMON_MAX_MESSAGE_BYTES = 1 << 20


def session_config(listen: list[str], connect: list[str], multicast_scouting: bool = False,
                   max_message_bytes: int | None = None) -> zenoh.Config:
    """Peer-mode config; multicast scouting is off unless explicitly enabled. With
    `max_message_bytes` (the daemon), larger messages are dropped by the transport and shared
    memory is off, so that no payload bypasses that limit (Zenoh moves large messages between
    processes of one host through shared memory, unfragmented)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    if max_message_bytes is not None:
        conf.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
        conf.insert_json5("transport/shared_memory/enabled", "false")
    return conf


class Keys:
    def __init__(self, robot: str):
        base = f"tecdar/{robot}"
        self.state = f"{base}/state"
        self.contact = f"{base}/contact"
        self.events = f"{base}/events"
        self.alive = f"{base}/alive"
        self.cmd_prefix = f"{base}/cmd/"
        self.cmd_all = f"{base}/cmd/**"     # every key under cmd/: unknown verbs get an unknown_verb reply

    def cmd(self, verb: str) -> str:
        return self.cmd_prefix + verb


def dumps(obj) -> str:
    return json.dumps(obj, separators=(",", ":"))
