"""Zenoh session configuration and the `tecdar/1` key expressions."""
from __future__ import annotations

import json

import zenoh

JSON = zenoh.Encoding.APPLICATION_JSON


def session_config(listen: list[str], connect: list[str], multicast_scouting: bool = False) -> zenoh.Config:
    """Peer-mode config; multicast scouting is off unless explicitly enabled."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


class Keys:
    def __init__(self, robot: str):
        base = f"tecdar/{robot}"
        self.state = f"{base}/state"
        self.contact = f"{base}/contact"
        self.events = f"{base}/events"
        self.alive = f"{base}/alive"
        self.cmd_prefix = f"{base}/cmd/"
        self.cmd_all = f"{base}/cmd/*"

    def cmd(self, verb: str) -> str:
        return self.cmd_prefix + verb


def dumps(obj) -> str:
    return json.dumps(obj, separators=(",", ":"))
