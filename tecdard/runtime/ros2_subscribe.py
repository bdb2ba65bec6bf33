"""The ROS 2 node's subscriptions (the observer backend's): the arm's joint states and, where configured, its wrench
at the TCP. Each message is decoded on Zenoh's thread and handed to the backend's handler, which judges it; a
handler never sees an exception, only `(msg, None, source)` or `(None, problem)`."""
from __future__ import annotations

import math
import time

from tecdard.ros2 import rmw
from tecdard.ros2.typesupport import TypeError_
from tecdard.runtime.ros2_parameters import _bytes

JOINT_STATE = "sensor_msgs/msg/JointState"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
SUBSCRIPTION_QOS = rmw.SENSOR_DATA      # best effort: takes a reliable or a best-effort publisher
MAX_BYTES = {JOINT_STATE: 16384,        # 64 joints with long names fit; larger is no arm's
             WRENCH_STAMPED: 1024}      # a header and six doubles: a frame id of hundreds of bytes at most


def subscribe(node, topic: str, ros_type: str, handler, counter: str, min_period_s: float = 0.0) -> None:
    """Declare `node`'s subscription to `topic` (its token, then Zenoh's subscriber). A message within
    `min_period_s` of the last one taken is dropped first, undecoded (the control tick reads one state a tick);
    one larger than MAX_BYTES is refused undecoded; the publisher's GID comes from rmw_zenoh's attachment.
    node.counters[counter], [counter + "_decimated"] and ["bad_" + counter] count them."""
    key, _ = node._entity(rmw.SUBSCRIPTION, topic, ros_type, SUBSCRIPTION_QOS)
    taken = [-math.inf]
    limit = MAX_BYTES[ros_type]
    counters = node.counters
    for name in (counter, counter + "_decimated", "bad_" + counter):
        counters.setdefault(name, 0)

    def on_sample(sample) -> None:
        counters[counter] += 1
        now = time.monotonic()
        if now - taken[0] < min_period_s:
            counters[counter + "_decimated"] += 1
            return
        taken[0] = now
        size = len(sample.payload)
        if size > limit:
            counters["bad_" + counter] += 1
            handler(None, f"{ros_type}: {size} bytes, more than an arm's (at most {limit})")
            return
        try:
            source = rmw.parse_attachment(_bytes(sample.attachment))[2]
        except ValueError:
            source = None
        try:
            msg = node.ts.decode(sample.payload.to_bytes(), ros_type)
        except TypeError_ as exc:
            counters["bad_" + counter] += 1
            handler(None, str(exc))
            return
        except Exception as exc:
            counters["bad_" + counter] += 1
            handler(None, f"{ros_type}: {type(exc).__name__}")
            return
        handler(msg, None, source)
    node._declared.append(node.session.declare_subscriber(key, on_sample))
