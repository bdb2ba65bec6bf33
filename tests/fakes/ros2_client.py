"""An independent rmw_zenoh client in a process of its own: zenoh-ros2-sdk (ROBOTIS), for the ROS 2 tests.

The SDK keeps one Zenoh session per process (a singleton) and fetches message definitions from the
network unless they are on disk: this process points its registry at the ROS 2 wheels' own
definitions (`<venv>/share/<package>/msg|srv`) and at the project's tecdar_msgs, with its clone cache
in a temporary folder, so nothing reaches the network. Multicast scouting is off and it listens on
loopback only (ZENOH_CONFIG_OVERRIDE, which the SDK reads).

    python -m tests.fakes.ros2_client ROUTER_PORT ACTION [ARGS as JSON]

Actions print one JSON line each:
- `discover` {"timeout"}: the tokens, topics and services the SDK's discovery sees (asked again until
  it sees topics and services, or `timeout`).
- `subscribe` {"topic", "type", "count", "timeout"}: {"subscribed"} once it is, then the first `count`
  messages (or all that came within `timeout`), as dicts; with {"topics": [[topic, type, count], ...]}
  several at once, the messages by topic. Each message carries "_rx", when it arrived (system clock).
- `call` {"service", "type", "request", "timeout", "request_definition", "response_definition"}: the
  response, as a dict (null: no reply).
- `publish` {"topic", "type", "message", "count", "period_s"}: publishes the JointState `message` (a
  dict; stamp "now": each time it is sent) `count` times, `period_s` apart.
"""
from __future__ import annotations

import json
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]
TFMESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms\n"     # tf2_msgs/msg/TFMessage.msg as tf2_msgs ships it


def definitions_dir() -> str:
    """A folder <package>/msg|srv/*: the wheels' stock definitions and tecdar_msgs, linked."""
    share = pathlib.Path(sys.prefix) / "share"
    out = pathlib.Path(tempfile.mkdtemp(prefix="ros2-defs-"))
    for pkg in share.iterdir():
        if (pkg / "msg").is_dir() or (pkg / "srv").is_dir():
            (out / pkg.name).symlink_to(pkg)
    (out / "tecdar_msgs").symlink_to(ROOT / "ros2" / "tecdar_msgs")
    tf = out / "tf2_msgs" / "msg"          # no ros-tf2-msgs wheel: its one message, as tf2_msgs ships it
    tf.mkdir(parents=True)
    (tf / "TFMessage.msg").write_text(TFMESSAGE_MSG)
    return str(out)


def to_dict(msg):
    """A rosbags message as plain JSON values."""
    if hasattr(msg, "__dataclass_fields__"):
        return {k: to_dict(getattr(msg, k)) for k in msg.__dataclass_fields__ if k != "__msgtype__"}
    if hasattr(msg, "tolist"):
        return msg.tolist()
    if isinstance(msg, (list, tuple)):
        return [to_dict(x) for x in msg]
    if isinstance(msg, float) and msg != msg:
        return "nan"
    return msg


def main() -> None:
    port, action = int(sys.argv[1]), sys.argv[2]
    args = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
    os.environ["ZENOH_CONFIG_OVERRIDE"] = ('scouting/multicast/enabled=false;listen/endpoints=["tcp/127.0.0.1:0"];'
                                           'connect/retry={"period_init_ms":100,"period_max_ms":200}')
    os.environ["ZENOH_ROS2_SDK_CACHE"] = tempfile.mkdtemp(prefix="ros2-sdk-cache-")
    import zenoh_ros2_sdk as sdk
    sdk.get_registry(definitions_dir())
    if action == "discover":
        from zenoh_ros2_sdk import ZenohSession
        session = ZenohSession.get_instance("127.0.0.1", port)
        t_end = time.monotonic() + args.get("timeout", 10.0)
        last = None
        while True:             # as a user runs `ros2 topic list` again while the graph settles: until two looks agree
            tokens = [str(r.ok.key_expr) for r in session.liveliness.get("@ros2_lv/**", timeout=1.0)
                      if r.ok is not None]
            topics = sdk.get_topic_names_and_types(router_port=port, timeout=1.0)
            services = sdk.get_service_names_and_types(router_port=port, timeout=1.0)
            look = (sorted(map(str, topics)), sorted(map(str, services)))
            if (topics and services and look == last) or time.monotonic() > t_end:
                break
            last = look
            time.sleep(0.2)
        print(json.dumps({"tokens": tokens, "topics": topics, "services": services}), flush=True)
    elif action == "subscribe":
        # one topic {"topic", "type", "count"}, or several {"topics": [[topic, type, count], ...]} in one session
        wanted = args.get("topics") or [[args["topic"], args["type"], args.get("count", 1)]]
        got = {topic: [] for topic, _, _ in wanted}
        subs = [sdk.ROS2Subscriber(topic, typ, lambda m, t=topic: got[t].append({**to_dict(m), "_rx": time.time()}),
                                   router_port=port,
                                   node_name="tecdar_test_listener") for topic, typ, _ in wanted]
        print(json.dumps({"subscribed": [w[0] for w in wanted]}), flush=True)
        t_end = time.monotonic() + args.get("timeout", 10.0)
        while any(len(got[t]) < n for t, _, n in wanted) and time.monotonic() < t_end:
            time.sleep(0.01)
        for sub in subs:
            sub.close()
        if "topics" in args:
            print(json.dumps({"messages": {t: got[t][:n] for t, _, n in wanted}}), flush=True)
        else:
            print(json.dumps({"messages": got[args["topic"]][:args.get("count", 1)]}), flush=True)
    elif action == "call":
        # a service with an empty request (std_srvs/Trigger) is given its definitions: the SDK's loader
        # refuses an empty request part of a .srv file
        cli = sdk.ROS2ServiceClient(args["service"], args["type"], router_port=port, timeout=args.get("timeout", 10.0),
                                    node_name="tecdar_test_client", request_definition=args.get("request_definition"),
                                    response_definition=args.get("response_definition"))
        time.sleep(args.get("settle_s", 0.5))
        res = cli.call(**request(args.get("request", {})))
        print(json.dumps({"response": None if res is None else to_dict(res)}), flush=True)
        cli.close()
    elif action == "publish":
        pub = sdk.ROS2Publisher(args["topic"], args["type"], router_port=port, node_name="tecdar_test_arm")
        time.sleep(args.get("settle_s", 0.5))
        t_next = time.monotonic()
        for _ in range(args["count"]):          # on an absolute schedule, as a driver publishes
            pub.publish(**joint_state(pub.session_mgr.store.types, args["message"]))
            t_next += args.get("period_s", 0.01)
            time.sleep(max(0.0, t_next - time.monotonic()))
        print(json.dumps({"published": args["count"]}), flush=True)
        pub.close()
    os._exit(0)           # the SDK's session threads would hold the process open


def request(fields: dict) -> dict:
    """Request fields from JSON: lists as float64 arrays (`grid`: int32; of strings: as they are), "nan" and "inf" as
    floats."""
    import numpy as np
    out = {}
    for k, v in fields.items():
        if isinstance(v, list) and all(isinstance(x, str) for x in v) and v:
            v = list(v)                              # string[] (a parameter request's names)
        elif isinstance(v, list):
            v = np.array([float(x) for x in v], dtype=np.int32 if k == "grid" else np.float64)
        elif v in ("nan", "inf", "-inf"):
            v = float(v)
        out[k] = v
    return out


def joint_state(types, msg: dict) -> dict:
    """A JointState as dicts (stamp "now": the system clock's time, or [sec, nanosec]) as the SDK's
    message classes: the header an object, the arrays float64."""
    import numpy as np
    hdr = msg.get("header", {})
    if hdr.get("stamp") == "now":
        t = time.time_ns() + int(hdr.get("offset_s", 0.0) * 1e9)
        sec, nsec = t // 10**9, t % 10**9
    else:
        sec, nsec = hdr.get("stamp", [0, 0])
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                          frame_id=hdr.get("frame_id", ""))
    return {"header": header, "name": list(msg.get("name", [])),
            **{k: np.array([float(x) for x in msg.get(k, [])], dtype=np.float64)
               for k in ("position", "velocity", "effort")}}


if __name__ == "__main__":
    main()
