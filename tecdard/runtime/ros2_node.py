"""tecdard as a ROS 2 node over rmw_zenoh, on the daemon's own Zenoh session (interface `tecdar-ros2/1`).

The node declares its liveliness tokens (the node and every entity, with QoS), publishes CDR samples
with rmw_zenoh's attachment, serves its services as Zenoh queryables, and subscribes to joint states
for the observer backend. Everything it encodes it encodes on the main thread's publish pass
(`on_telemetry`, `publish_pending`, `poll`): the estimator thread only hands over its passes
(`feed`, never blocking), and the control tick never sees the node.

Services go through the daemon's own command intake (tecdard.runtime.intake.QueryIntake): a request
becomes the Zenoh interface's JSON payload of the same verb, with the same size check, rate limit,
validation, limits, refusals and replies; `stop` is handed to the control thread from Zenoh's
callback, as the Zenoh `stop` is.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from tecdard import verbs as task_verbs
from tecdard.options import option, read_options
from tecdard.ros2 import messages as M
from tecdard.ros2 import parameters as P
from tecdard.ros2 import rmw
from tecdard.ros2.typesupport import DISTROS, TypeError_, TypeSupport, dds_type_name
from tecdard.runtime.ros2_actions import ActionServer, matching
from tecdard.runtime.ros2_parameters import _bytes, queued
from tecdard.runtime.ros2_subscribe import JOINT_STATE, WRENCH_STAMPED, subscribe
from tecdard.runtime.main_loop import FrontDoor
from tecdard.runtime.messages import Inbox

log = logging.getLogger("tecdar.ros2")

TRIGGER = "std_srvs/srv/Trigger"
TRIGGER_SRV = "---\nbool success\nstring message\n"     # std_srvs/srv/Trigger, as std_srvs ships it
# topic (relative to the namespace, or absolute) -> (type, QoS)
TOPICS = {
    "contact": ("geometry_msgs/msg/PoseWithCovarianceStamped", rmw.RELIABLE_10),
    "contact_marker": ("visualization_msgs/msg/Marker", rmw.RELIABLE_10),
    "imu": ("sensor_msgs/msg/Imu", rmw.SENSOR_DATA),
    "tcp_pose": ("geometry_msgs/msg/PoseStamped", rmw.SENSOR_DATA),
    "wrench": ("geometry_msgs/msg/WrenchStamped", rmw.SENSOR_DATA),
    "events": ("tecdar_msgs/msg/Event", rmw.RELIABLE_10),
    "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", rmw.RELIABLE_10),
    "/tf": ("tf2_msgs/msg/TFMessage", rmw.TF_QOS),
}
SERVICE_QOS = rmw.RELIABLE_10           # rmw_qos_profile_services_default
SERVICE_BACKLOG = 16                    # requests waiting per service (the oldest overwritten)
TAP_PASSES = 256                        # estimator passes waiting for the publish pass; more are dropped
IMU_BLOCKS_PER_PASS = 200               # averaged IMU messages published per pass at most (a backlog is dropped)
DIAGNOSTICS_PERIOD_S = 1.0
CONTROL_LATE_WARN_MS = 5.0              # diagnostics: a control tick this late (p99) is a warning


@dataclass(frozen=True)
class Ros2Params:
    """The `ros2` section: the daemon as a ROS 2 node over rmw_zenoh (docs/ros2.md)."""
    enabled: bool = option(False, "the node declares its topics and services")
    distro: str = option("kilted", "the ROS 2 distribution (the type hash in every key)", choices=DISTROS)
    domain_id: int = option(0, "ROS_DOMAIN_ID", minval=0, maxval=232)
    namespace: str = option("", "the node's namespace; \"\": /ROBOT_NAME (robot.name, a '-' in it as '_')", max_len=200)
    node_name: str = option("tecdard", "the node's name", max_len=100)
    base_frame: str = option("base_link", "frame_id of every position in the robot's base frame", max_len=200)
    tcp_frame: str = option("tcp", "the TCP's tf2 frame", max_len=200)
    imu_frame: str = option("fingertip_imu", "the fingertip IMU's tf2 frame", max_len=200)
    imu_rate_hz: float = option(1000.0, "the fingertip IMU republished, block-averaged; 0: not published",
                                unit="Hz", minval=0.0, maxval=10000.0)
    joint_states: str = option("/joint_states", "the topic robot.backend ros2 reads the arm's joint states from",
                               max_len=200)
    wrench: str = option("", "the topic robot.backend ros2 reads the arm's own wrench at the TCP from "
                             "(geometry_msgs/WrenchStamped in base_frame; \"\": none)", max_len=200)

    @classmethod
    def from_config(cls, section, robot: str) -> "Ros2Params":
        p = read_options(cls, section)
        # by default the robot's name, made a ROS 2 name: a fleet's `ur5e-left` is /ur5e_left
        namespace = p.namespace or "/" + _ros_chunk(robot)
        if namespace != "/" and (not namespace.startswith("/") or not _ros_name(namespace.strip("/"), allow_slash=True)):
            raise section.error("namespace", f"{namespace!r} is no ROS 2 namespace (/name or /a/b: letters, "
                                             "digits and '_')")
        if not _ros_name(p.node_name):
            raise section.error("node_name", f"{p.node_name!r} is no ROS 2 node name (letters, digits and '_')")
        for key in ("joint_states", "wrench"):
            topic = getattr(p, key)
            if (topic or key == "joint_states") and not _ros_name(topic.lstrip("/"), allow_slash=True):
                raise section.error(key, f"{topic!r} is no ROS 2 topic name")
        for key in ("base_frame", "tcp_frame", "imu_frame"):
            frame = getattr(p, key)
            if not frame or frame.startswith("/"):
                raise section.error(key, f"{frame!r}: a tf2 frame id is not empty and has no leading '/'")
        return dataclasses.replace(p, namespace=namespace.rstrip("/") or "/")


def _ros_chunk(name: str) -> str:
    """`name` as one ROS 2 name chunk: '-' (and any other character ROS 2 refuses) as '_', and a leading
    digit behind an 'r_'."""
    chunk = "".join(c if c.isascii() and (c.isalnum() or c == "_") else "_" for c in name) or "tecdar"
    return f"r_{chunk}" if chunk[0].isdigit() else chunk


def _ros_name(name: str, allow_slash: bool = False) -> bool:
    chunks = name.split("/") if allow_slash else [name]
    return all(c and (c[0].isalpha() or c[0] == "_") and c.replace("_", "").isalnum() and c.isascii()
               for c in chunks)


class ServiceCall:
    """A ROS 2 service request as the intake sees a Zenoh query: the command's key, its JSON payload,
    and `reply`, which answers in CDR with the request's sequence number and client GID."""

    def __init__(self, node: "Ros2Node", service: "_Service", query, cmd_key: str, payload: bytes,
                 seq: int, client_gid: bytes):
        self.node, self.service, self.query = node, service, query
        self.key_expr, self.payload = cmd_key, payload
        self.seq, self.client_gid = seq, client_gid

    def reply(self, _key, text: str, encoding=None) -> None:
        self.node.answer(self, json.loads(text))
        self.query = None          # dropping the Zenoh query sends its final reply


@dataclass
class _Service:
    verb: str            # its name, relative to the namespace
    srv_type: str
    key: str
    ring: object = None


class Ros2Node(FrontDoor):
    """Owned by the main thread, but for `feed` (the estimator thread) and the stop and joint-state
    callbacks (Zenoh's threads), which only hand over."""

    def __init__(self, params: Ros2Params, robot: str, intake, types: TypeSupport | None = None):
        self.params, self.robot, self.intake = params, robot, intake
        self.ts = types or TypeSupport(params.distro)
        self.ts.add_service(TRIGGER_SRV, TRIGGER)
        for srv_type, text in P.SRV_TEXTS.items():
            self.ts.add_service(text, srv_type)
        self.param_server = None     # runtime.ros2_parameters.ParameterServer: the config as parameters
        self.actions: ActionServer | None = None     # the task verbs as actions, once declared
        self.types_in_use: dict[str, str] = {}       # every type of an entity declared -> its hash
        self._inbox = Inbox(TAP_PASSES)
        self._declared: list = []
        self._pubs: dict[str, tuple] = {}         # topic -> (zenoh publisher, gid, [seq], type)
        self._services: list[_Service] = []
        self._stop: _Service | None = None
        self._imu_acc = _BlockAverage(params.imu_rate_hz)
        self._latest_state: dict | None = None
        self._diag_next = 0.0
        self._clock_offset_s = time.time() - time.monotonic()
        self._clock_next = 0.0
        self.counters = {"published": 0, "requests": 0, "bad_requests": 0, "joint_states": 0, "bad_joint_states": 0,
                         "joint_states_decimated": 0}          # and "wrench", "bad_wrench", where subscribed
        self.node: rmw.NodeInfo | None = None
        self._entities = 0

    def acl_keys(self, subscribes: bool) -> dict:
        """The node's key expressions for the daemon's access control (tecdard.api.session): what it
        publishes, its tokens, its services and (`subscribes`) the joint-state topic."""
        p = self.params
        ns = p.namespace.strip("/")
        mine = f"{p.domain_id}/{ns}/**" if ns else f"{p.domain_id}/**"
        out = {"publish": [mine] + [f"{p.domain_id}/{t.strip('/')}/**" for t in TOPICS if t.startswith("/")],
               "tokens": [f"{rmw.ADMIN_SPACE}/{p.domain_id}/**"], "serve": [mine]}
        if subscribes:
            out["subscribe"] = [f"{p.domain_id}/{t.strip('/')}/**" for t in (p.joint_states, p.wrench) if t]
        return out

    # -- declaring ------------------------------------------------------------------------------
    def declare(self, session: zenoh.Session, joint_states=None, joint_states_period_s: float = 0.0,
                wrench=None) -> None:
        """The node's token, its publishers, services and (with `joint_states(msg | None, problem)`, the
        observer backend's handler) its joint-state subscription, which drops messages closer together than
        `joint_states_period_s` before decoding them; with `wrench` (the backend's handler) and `ros2.wrench`
        set, the arm's wrench at the TCP."""
        p = self.params
        self.session = session
        self.node = rmw.NodeInfo(p.domain_id, str(session.info.zid()), 0, "" if p.namespace == "/" else p.namespace,
                                 p.node_name)
        self._token(self.node.token())
        for topic, (ros_type, qos) in TOPICS.items():
            if topic == "imu" and p.imu_rate_hz == 0:
                continue
            key, token = self._entity(rmw.PUBLISHER, topic, ros_type, qos)
            self._pubs[topic] = (session.declare_publisher(key), rmw.gid(token), [0], ros_type)
            self._declared.append(self._pubs[topic][0])
        for verb, srv_type in self._service_types():
            key, _ = self._entity(rmw.SERVICE, verb, srv_type, SERVICE_QOS)
            svc = _Service(verb, srv_type, key)
            if verb == "stop":
                svc.ring = session.declare_queryable(key, lambda q, s=svc: self._on_stop(s, q), complete=True)
                self._stop = svc
            else:
                svc.ring = session.declare_queryable(key, zenoh.handlers.RingChannel(SERVICE_BACKLOG), complete=True)
                self._services.append(svc)
            self._declared.append(svc.ring)
        if self.param_server is not None:
            self.param_server.declare(session)
        self.actions = ActionServer(self)
        self.actions.declare(session)
        if joint_states is not None:
            subscribe(self, p.joint_states, JOINT_STATE, joint_states, "joint_states", joint_states_period_s)
        if wrench is not None and p.wrench:
            subscribe(self, p.wrench, WRENCH_STAMPED, wrench, "wrench")
        log.info("ROS 2 node %s/%s on domain %d (%s): %d topics, %d services, %d actions", self.node.namespace,
                 p.node_name, p.domain_id, p.distro, len(self._pubs), len(self._services) + 1,
                 len(self.actions.actions))

    def set_parameters(self, config_data: dict, sections: list) -> None:
        """The daemon's config as the node's read-only parameters (tecdard/ros2/parameters.py), before `declare`;
        `sections`: tecdard.runtime.option_sections.sections()."""
        from tecdard.runtime.ros2_parameters import ParameterServer
        self.param_server = ParameterServer(self, P.ParameterSet(config_data, sections))

    def _service_types(self) -> list[tuple[str, str]]:
        """(verb, service type) of every service: a task verb without its .srv in tecdar_msgs (a verb
        added without one) is not served, and said so."""
        out = [("stop", TRIGGER)]
        for verb in task_verbs.names():
            srv_type = f"tecdar_msgs/srv/{verb.capitalize()}"
            if srv_type in self.ts.services:
                out.append((verb, srv_type))
            else:
                log.warning("ROS 2: no %s in tecdar_msgs: the verb %s is not served over ROS 2", srv_type, verb)
        return out + [("cancel", "tecdar_msgs/srv/Cancel"), ("status", "tecdar_msgs/srv/Status")]

    def _token(self, key: str) -> None:
        self._declared.append(self.session.liveliness().declare_token(key))

    def _entity(self, kind: str, name: str, ros_type: str, qos: rmw.Qos) -> tuple[str, str]:
        """The data key of a topic or service, after declaring its liveliness token; and the token."""
        self._entities += 1
        fq = rmw.fully_qualified(self.node.namespace, name)
        dds, type_hash = dds_type_name(ros_type), self.ts.type_hash(ros_type)
        self.types_in_use[ros_type] = type_hash        # ~/get_type_description describes these
        token = rmw.entity_token(self.node, self._entities, kind, fq, dds, type_hash, qos)
        self._token(token)
        return rmw.data_keyexpr(self.params.domain_id, fq, dds, type_hash), token

    def undeclare(self) -> None:
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:
                log.debug("undeclaring a ROS 2 entity failed", exc_info=True)
        self._declared.clear()
        self._pubs.clear()
        self._services.clear()

    # -- the estimator's tap (its thread) ---------------------------------------------------------
    def feed(self, p) -> None:
        """An estimator pass (its IMU batch and estimate): queued, never blocking."""
        if len(p.batch) or p.estimate is not None:
            self._inbox.put(p)

    # -- publishing (the main thread) ---------------------------------------------------------------
    def wall(self, t_mono: float) -> float:
        """A monotonic time on the system clock (ROS time), the offset taken again every second."""
        return t_mono + self._clock_offset_s

    def on_telemetry(self, kind: str, body: dict, text: str) -> None:
        """One message of the Zenoh interface as it is published: `state` -> tcp_pose, `event` -> events."""
        try:
            if self.actions is not None:
                self.actions.on_telemetry(kind, body)
            if kind == "state":
                self._latest_state = body
                t = body["t"] if body.get("tcp_t") is None else body["tcp_t"]
                if self._wanted("tcp_pose"):
                    tcp = body["tcp"]
                    self._put("tcp_pose", M.tcp_pose(self.ts, tcp["p"], tcp["q"], self.wall(t), self.params.base_frame))
                w = body.get("wrench")
                if w is not None and self._wanted("wrench"):
                    self._put("wrench", M.wrench(self.ts, w["force_n"], w["torque_nm"], self.wall(t),
                                                 self.params.base_frame))
            elif kind == "event":
                t = body.get("t")
                t = float(t) if isinstance(t, (int, float)) and math.isfinite(t) else time.monotonic()
                self._put("events", M.event(self.ts, body, self.wall(t), text))
        except Exception:
            log.exception("ROS 2: a %s message was not published", kind)

    def publish_pending(self, now: float) -> None:
        """The estimator's passes since the last call: averaged IMU blocks, then the newest contact
        (contact, contact_marker, /tf); and /diagnostics once a second."""
        if now >= self._clock_next:
            self._clock_offset_s = time.time() - time.monotonic()
            self._clock_next = now + 1.0
        passes = self._inbox.drain()
        try:
            if self._wanted("imu"):
                batches = [p.batch for p in passes if len(p.batch)]
                if batches:
                    blocks = self._imu_acc.add(np.concatenate(batches))
                    for t, gyro, accel in blocks[-IMU_BLOCKS_PER_PASS:]:
                        self._put("imu", M.imu(self.ts, self.wall(t), gyro, accel, self.params.imu_frame))
            else:
                self._imu_acc.reset()
            est = next((p.estimate for p in reversed(passes) if p.estimate is not None), None)
            if est is not None and (self._wanted("contact") or self._wanted("contact_marker") or self._wanted("/tf")):
                t, q, base = self.wall(est.t), M.axis_quat(est.axis), self.params.base_frame
                self._put("contact", M.contact(self.ts, est, t, base, q))
                for marker in M.contact_markers(self.ts, est, t, base, q):
                    self._put("contact_marker", marker)
                self._put("/tf", M.contact_tf(self.ts, est, t, base, f"{self.robot}/contact", q))
            if now >= self._diag_next:
                self._diag_next = now + DIAGNOSTICS_PERIOD_S
                self._put("/diagnostics", M.diagnostics(self.ts, self.wall(now), self._statuses()))
        except Exception:
            log.exception("ROS 2: a publish pass failed")

    def _wanted(self, topic: str) -> bool:
        """Whether anyone subscribes to `topic` (Zenoh's matching status, about 1 µs): a message nobody
        takes is neither built nor encoded."""
        pub = self._pubs.get(topic)
        return pub is not None and matching(pub[0])

    def _put(self, topic: str, msg) -> None:
        pub, gid, seq, ros_type = self._pubs[topic]
        seq[0] += 1
        pub.put(self.ts.encode(msg, ros_type), attachment=rmw.attachment(seq[0], time.time_ns(), gid))
        self.counters["published"] += 1

    def _statuses(self) -> list:
        state = self._latest_state or {}
        ctl = state.get("control") or {}
        faults = state.get("faults") or []
        codes = [f.get("code", "") for f in faults]
        imu_faults = [c for c in codes if c.startswith("imu")]
        robot_faults = [c for c in codes if c.startswith("robot")]
        prefix = f"tecdard/{self.robot}: "
        late = ctl.get("late_ms_p99")
        late_level = M.WARN if isinstance(late, (int, float)) and late > CONTROL_LATE_WARN_MS else M.OK
        contact = state.get("contact") or {}
        return [
            (prefix + "fingertip IMU", M.ERROR if imu_faults else M.OK, ", ".join(imu_faults) or "streaming",
             {"ring_overwritten": ctl.get("imu_overwritten", ""), "ros2_passes_dropped": self._inbox.dropped}),
            (prefix + "estimator", M.OK, "tracking a contact" if contact else "no contact",
             {"converged": contact.get("converged", ""), "method": contact.get("method", "")}),
            (prefix + "control", late_level if not ctl.get("overruns") else M.WARN, state.get("mode", "no state yet"),
             {k: ctl.get(k, "") for k in ("ticks", "overruns", "late_ms_p99", "work_ms_p99")}),
            (prefix + "faults", M.ERROR if faults else M.OK, "; ".join(codes) or "none",
             {f.get("code", ""): f.get("message", "") for f in faults}),
            (prefix + "robot link", M.ERROR if robot_faults else M.OK, ", ".join(robot_faults) or "ok",
             {"mode": state.get("mode", ""), **{k: v for k, v in self.counters.items() if "joint" in k}}),
        ]

    # -- services ---------------------------------------------------------------------------------------
    def _call(self, svc: _Service, query, now: float | None = None) -> ServiceCall | None:
        """A query as a ServiceCall; None (and an error reply where one can be sent) when it is no request.
        With `now` (the queued services; not a stop), the request is charged to its class's budget, and checked
        against the size limit, before its CDR is decoded: a flood of large requests costs the main thread no
        more than the Zenoh interface's does."""
        self.counters["requests"] += 1
        try:
            seq, _t, client_gid = rmw.parse_attachment(_bytes(query.attachment))
        except ValueError as exc:
            self.counters["bad_requests"] += 1
            log.info("ROS 2 %s: request refused: %s", svc.verb, exc)
            return None
        key = self.intake.keys.cmd(svc.verb)
        if now is not None:
            size = len(query.payload) if query.payload is not None else 0
            if not self.intake.charge(ServiceCall(self, svc, query, key, b"", seq, client_gid), key, size, now):
                return None
        try:
            raw = _bytes(query.payload) or b""
            if svc.verb in ("stop", "status"):
                payload = b""
            else:
                req = self.ts.decode(raw, svc.srv_type + "_Request")
                payload = self._payload(svc, req)
        except (TypeError_, ValueError) as exc:
            self.counters["bad_requests"] += 1
            call = ServiceCall(self, svc, query, self.intake.keys.cmd(svc.verb), b"", seq, client_gid)
            self.answer(call, {"ok": False, "error": {"code": "bad_request", "message": str(exc)}})
            return None
        return ServiceCall(self, svc, query, self.intake.keys.cmd(svc.verb), payload, seq, client_gid)

    @staticmethod
    def _payload(svc: _Service, req) -> bytes:
        if svc.verb == "cancel":
            return json.dumps({"task": req.task} if req.task else {}).encode()
        spec = task_verbs.get(svc.verb)
        return json.dumps(M.request_payload(spec.fields, req)).encode()

    def _on_stop(self, svc: _Service, query) -> None:
        """Zenoh's callback thread: a stop goes to the control thread at once, as the Zenoh stop does."""
        call = self._call(svc, query)
        if call is not None:
            self.intake.on_stop(call)

    def poll(self, now: float) -> int:
        """The services' queued requests, each through the intake as its Zenoh verb."""
        n = 0
        for svc, query in queued(self._services, SERVICE_BACKLOG):
            n += 1
            call = self._call(svc, query, now)
            if call is not None:
                self.intake.handle(call, call.key_expr, call.payload, now, charged=True)
        if self.param_server is not None:
            n += self.param_server.poll(now)
        if self.actions is not None:
            n += self.actions.poll(now)
        return n

    def answer(self, call: ServiceCall, reply: dict) -> None:
        """The reply of the Zenoh interface as the service's CDR response (any thread that replies)."""
        svc = call.service
        try:
            if svc.srv_type == TRIGGER:
                msg = M.trigger_response(self.ts, reply)
            elif svc.verb == "status":
                msg = M.status_response(self.ts, svc.srv_type, reply)
            else:
                msg = M.task_response(self.ts, svc.srv_type, reply)
            payload = self.ts.encode(msg, svc.srv_type + "_Response")
            att = rmw.attachment(call.seq, time.time_ns(), call.client_gid)
            if call.query is not None:
                call.query.reply(call.query.key_expr, payload, attachment=att)
        except Exception:
            log.exception("ROS 2 %s: the reply was not sent", svc.verb)


class _BlockAverage:
    """IMU samples averaged over blocks of 1/rate_hz on an absolute time grid: a block is published
    once a sample of a later block arrives (its mean time, gyro and accel)."""

    def __init__(self, rate_hz: float):
        self.rate_hz = rate_hz
        self._held = np.zeros((0, 7))

    def reset(self) -> None:
        """Forget the samples held (nobody subscribes: the next block starts afresh)."""
        self._held = np.zeros((0, 7))

    def add(self, batch: np.ndarray) -> list[tuple[float, np.ndarray, np.ndarray]]:
        if self.rate_hz <= 0:
            return []
        b = np.concatenate([self._held, batch]) if len(self._held) else batch
        bins = np.floor(b[:, 0] * self.rate_hz)
        last = bins[-1]
        done = bins < last
        self._held = b[~done]
        b, bins = b[done], bins[done]
        if not len(b):
            return []
        starts = np.flatnonzero(np.r_[True, bins[1:] != bins[:-1]])
        counts = np.diff(np.r_[starts, len(b)])
        sums = np.add.reduceat(b, starts, axis=0)
        means = sums / counts[:, None]
        return [(float(m[0]), m[1:4], m[4:7]) for m in means]
