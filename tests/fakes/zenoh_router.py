"""A Zenoh router on loopback, as a ROS 2 host runs `rmw_zenohd`: eclipse-zenoh's own router mode, in a
process of its own, for the ROS 2 tests.   python -m tests.fakes.zenoh_router PORT"""
import sys
import threading

import zenoh

from tecdard.api.session import session_config


def main() -> None:
    conf = session_config([f"tcp/127.0.0.1:{int(sys.argv[1])}"], [], mode="router")
    with zenoh.open(conf):
        print("router ready", flush=True)
        threading.Event().wait()


if __name__ == "__main__":
    main()
