"""The live Foxglove view (issue 20): a WebSocket client, as Foxglove Studio would, subscribes to every
channel of a running daemon and receives each."""
import json
import struct
import time

import pytest

from tecdard.tools.demo import free_port
from tests.conftest import DaemonProcess, daemon_config

pytest.importorskip("foxglove", reason="the `viz` extra, which `make test` installs")
ws_client = pytest.importorskip("websockets.sync.client")

TOPICS = {"/imu", "/tf", "/contact", "/events", "/imu/mean"}     # the live view has no joints to send
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01                       # the binary opcode of a message on a subscription
RECEIVE_WITHIN_S = 20.0


def connect(port: int, within_s: float = 10.0):
    deadline = time.monotonic() + within_s
    while True:
        try:
            return ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=2.0)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@pytest.mark.slow
def test_a_websocket_client_receives_every_channel_of_the_live_view(tmp_path):
    port = free_port()
    d = DaemonProcess(tmp_path, daemon_config(**{"viz.foxglove": {"enabled": True, "port": port}}))
    try:
        with connect(port) as ws:
            channels = {}
            while set(channels) != TOPICS:
                msg = json.loads(ws.recv(timeout=5.0))
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
            assert channels["/contact"]["schemaName"] == "foxglove.SceneUpdate"
            assert channels["/imu"]["encoding"] == "json"
            subs = {k: channels[topic]["id"] for k, topic in enumerate(sorted(TOPICS), start=1)}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": k, "channelId": c} for k, c in subs.items()]}))
            reply = d.client.command("rotate", {"angle_deg": 10.0})      # an onset, estimates, events
            assert reply["ok"] is True
            got: dict = {}
            imu_samples = 0
            deadline = time.monotonic() + RECEIVE_WITHIN_S
            while len(got) < len(subs) and time.monotonic() < deadline:
                frame = ws.recv(timeout=5.0)
                if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                    sub, stamp_ns = struct.unpack_from("<IQ", frame, 1)
                    got.setdefault(sub, []).append(frame[13:])
                    if sub == {v: k for k, v in subs.items()}.get(channels["/imu"]["id"]):
                        imu_samples += len(json.loads(frame[13:])["t"])
                    assert stamp_ns > 1.5e18                 # wall-clock nanoseconds
        topics_got = {sorted(TOPICS)[k - 1] for k in got}
        assert topics_got == TOPICS, topics_got
        assert imu_samples > 0
    finally:
        d.close()
    assert "live view: Foxglove WebSocket server on ws://127.0.0.1:" in d.log()


@pytest.mark.slow
def test_a_live_view_whose_port_is_taken_leaves_the_daemon_running(tmp_path):
    import socket
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        d = DaemonProcess(tmp_path, daemon_config(**{"viz.foxglove": {"enabled": True, "port": port}}))
        try:
            assert d.client.command("status")["ok"] is True
        finally:
            d.close()
    assert "viz.foxglove: cannot serve on 127.0.0.1:%d" % port in d.log()


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024.0


@pytest.mark.slow
def test_viewers_that_never_read_are_capped_in_number_and_in_bytes(tmp_path):
    """150 viewers that never read took the daemon from 282 MB to 1.7 GB, and imu_stale came while
    idle (issue 32, item 9): beyond viz.foxglove.max_viewers a viewer is turned away (503), and what
    waits for one that does not read is bounded by viz.foxglove.viewer_buffer_mb."""
    from websockets.exceptions import InvalidStatus
    port = free_port()
    d = DaemonProcess(tmp_path, daemon_config(**{"viz.foxglove": {"enabled": True, "port": port, "max_viewers": 3,
                                                                  "viewer_buffer_mb": 1.0}}))
    viewers, refused = [], 0
    try:
        time.sleep(2.0)
        rss0 = rss_mb(d.proc.pid)
        for _ in range(12):
            try:
                # once a frame waits, nothing more is read; its close does not wait for the frames queued
                ws = ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5.0,
                                       max_queue=1, close_timeout=1.0)
            except InvalidStatus as exc:
                assert exc.response.status_code == 503
                refused += 1
                continue
            channels = {}
            while set(channels) != TOPICS:
                msg = json.loads(ws.recv(timeout=5.0))
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": k, "channelId": channels[topic]["id"]} for k, topic in enumerate(sorted(TOPICS), start=1)]}))
            viewers.append(ws)                 # and never read again
        assert len(viewers) == 3 and refused == 9
        time.sleep(15.0)                       # the IMU's 0.5 MB/s and the TCP's frames pile up for them
        grown = rss_mb(d.proc.pid) - rss0
        print(f"daemon RSS {rss0:.0f} MB, {grown:+.0f} MB after 15 s of 3 viewers that never read")
        assert grown < 60.0, f"{grown:.0f} MB for 3 viewers that never read"
        state = d.client.command("status")["state"]
        assert state["faults"] == [], state["faults"]
    finally:
        for ws in viewers:
            ws.close()
        d.close()
    assert "imu_stale" not in d.log()
    assert "a viewer turned away, 3 are connected (viz.foxglove.max_viewers)" in d.log()


def test_a_viewer_of_the_old_protocol_name_is_served():
    """Issue 50 item 16: Lichtblick and Foxglove builds before the SDK ask for `foxglove.websocket.v1`, which
    foxglove-sdk answered HTTP 400 (it knows the same protocol as `foxglove.sdk.v1` only). The gate renames it
    both ways: the viewer gets the name it asked for and the server's advertisements."""
    from tecdard.runtime.view_gate import rename_answer, rename_offer
    head = b"GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: foxglove.websocket.v1\r\nUpgrade: websocket"
    renamed, done = rename_offer(head)
    assert done and b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n" in renamed
    both = head.replace(b"foxglove.websocket.v1", b"foxglove.websocket.v1, foxglove.sdk.v1")
    assert rename_offer(both) == (both, False)               # the SDK's own name offered: nothing to rename
    assert rename_answer(b"HTTP/1.1 101\r\nsec-websocket-protocol: foxglove.sdk.v1") == \
        b"HTTP/1.1 101\r\nsec-websocket-protocol: foxglove.websocket.v1"


@pytest.mark.slow
def test_lichtblicks_protocol_name_receives_the_live_view(tmp_path):
    """A client offering only `foxglove.websocket.v1`, against the daemon's live view: it is accepted under that
    name, and the server's advertisement of every channel arrives."""
    port = free_port()
    d = DaemonProcess(tmp_path, daemon_config(**{"viz.foxglove": {"enabled": True, "port": port}}))
    try:
        deadline = time.monotonic() + 10.0
        while True:
            try:
                ws = ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],
                                       open_timeout=2.0)
                break
            except OSError:
                assert time.monotonic() < deadline
                time.sleep(0.1)
        with ws:
            assert ws.subprotocol == "foxglove.websocket.v1"
            topics: set = set()
            while topics != TOPICS:
                msg = json.loads(ws.recv(timeout=5.0))
                if msg.get("op") == "serverInfo":
                    assert msg["name"] == "tecdard"
                if msg.get("op") == "advertise":
                    topics |= {c["topic"] for c in msg["channels"]}
    finally:
        d.close()
