"""The ROS 2 node's own services, as rclcpp gives every node: the parameter services (which `ros2 param` calls)
and /parameter_events, the daemon's effective config read-only (tecdard/ros2/parameters.py); and
`~/get_type_description`, every type the node uses described (tecdard/ros2/type_description.py)."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import zenoh

from tecdard.ros2 import parameters as P
from tecdard.ros2 import type_description as TD
from tecdard.ros2 import rmw
from tecdard.ros2.typesupport import TypeError_

log = logging.getLogger("tecdar.ros2")

PARAMETER_EVENTS_QOS = rmw.Qos(rmw.RELIABLE, rmw.VOLATILE, rmw.KEEP_LAST, 1000)   # rmw_qos_profile_parameter_events
SERVICE_QOS = rmw.RELIABLE_10      # rmw_qos_profile_services_default
BACKLOG = 16                       # requests waiting per service (the oldest overwritten)


@dataclass
class _Service:
    verb: str                      # its name under the node's
    srv_type: str
    key: str
    ring: object = None


def queued(services: list, backlog: int):
    """(service, query) of each request waiting in the services' rings, at most `backlog` of each."""
    for svc in services:
        for _ in range(backlog):
            query = svc.ring.try_recv()
            if query is None:
                break
            yield svc, query


class _Unanswered:
    """A parameter request the intake's budget refuses: rcl_interfaces' services have no error reply; dropped."""
    key_expr = "ros2 parameter service"

    def reply(self, *_args, **_kwargs) -> None:
        pass


class ParameterServer:
    """The six services under the node's name and the one /parameter_events message, for `node` (a
    runtime.ros2_node.Ros2Node: its type support, entities, intake and counters)."""

    def __init__(self, node, params: P.ParameterSet):
        self.node, self.params = node, params
        self.services: list = []
        self._sources: dict[str, tuple[str, str]] | None = None

    def declare(self, session: zenoh.Session) -> None:
        node = self.node
        node.ts.add_service(TD.SRV_TEXT, TD.SERVICE)
        for name, srv_type in {**P.SERVICES, "get_type_description": TD.SERVICE}.items():
            key, _ = node._entity(rmw.SERVICE, f"{node.params.node_name}/{name}", srv_type, SERVICE_QOS)
            svc = _Service(name, srv_type, key)
            svc.ring = session.declare_queryable(key, zenoh.handlers.RingChannel(BACKLOG), complete=True)
            self.services.append(svc)
            node._declared.append(svc.ring)
        key, token = node._entity(rmw.PUBLISHER, "/parameter_events", P.PARAMETER_EVENT, PARAMETER_EVENTS_QOS)
        pub = session.declare_publisher(key)
        node._declared.append(pub)
        fqn = rmw.fully_qualified(node.node.namespace or "/", node.params.node_name)
        event = P.parameter_event(node.ts, self.params, fqn, time.time())
        pub.put(node.ts.encode(event, P.PARAMETER_EVENT), attachment=rmw.attachment(1, time.time_ns(), rmw.gid(token)))
        log.info("ROS 2 node %s: %d parameters (read-only)", fqn, len(self.params.params))

    def sources(self) -> dict[str, tuple[str, str]]:
        """tecdar_msgs' types -> (encoding, the .msg, .srv or .action text), read once."""
        if self._sources is None:
            from tecdard.ros2.typesupport import MSGS_DIR, PACKAGE
            self._sources = {f"{PACKAGE}/{kind}/{path.stem}": (kind, path.read_text()) for kind in ("msg", "srv", "action")
                             for path in sorted((MSGS_DIR / kind).glob(f"*.{kind}"))}
        return self._sources

    def poll(self, now: float) -> int:
        """Every queued request, answered (or dropped, over the budget or malformed); how many there were."""
        n = 0
        for svc, query in queued(self.services, BACKLOG):
            n += 1
            self.node.counters["requests"] += 1
            self._answer(svc, query, now)
        return n

    def _answer(self, svc, query, now: float) -> None:
        """One request: charged to the status class's budget before it is decoded (a flood is rate-limited as
        `status` is, unanswered), then answered from the set."""
        node = self.node
        try:
            seq, _t, client_gid = rmw.parse_attachment(_bytes(query.attachment))
        except ValueError:
            node.counters["bad_requests"] += 1
            return
        size = len(query.payload) if query.payload is not None else 0
        if not node.intake.charge(_Unanswered(), node.intake.keys.cmd("status"), size, now):
            return
        try:
            req = node.ts.decode(_bytes(query.payload) or b"", svc.srv_type + "_Request")
            if svc.srv_type == TD.SERVICE:
                msg = TD.respond(node.ts, node.types_in_use, self.sources(), req)
            else:
                msg = P.respond(node.ts, self.params, svc.srv_type, req)
            payload = node.ts.encode(msg, svc.srv_type + "_Response")
        except (TypeError_, ValueError) as exc:
            node.counters["bad_requests"] += 1
            log.info("ROS 2 %s: request refused: %s", svc.verb, str(exc)[:200])
            return
        query.reply(query.key_expr, payload, attachment=rmw.attachment(seq, time.time_ns(), client_gid))


def _bytes(z) -> bytes | None:
    return None if z is None else z.to_bytes()
