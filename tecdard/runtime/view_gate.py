"""The live view's front door: at most `max_viewers` Foxglove viewers, each with a bounded backlog.

foxglove-sdk's WebSocket server (0.30) takes every connection and queues up to
`message_backlog_size` messages per client, whatever their size; it has no cap on clients and no
byte limit. 150 viewers that never read cost the daemon about 8 MB each (282 MB to 1.7 GB), and
the sending starved the IMU path (`imu_stale` while idle).

So the server listens on a loopback port of its own, and the view's public port is this gate, a
byte relay on a thread of its own:
- a connection beyond `max_viewers` is answered `503 Service Unavailable` and closed;
- towards each viewer at most `buffer_bytes` wait in the relay. Past that the relay stops reading
  that viewer's side of the server, whose own queue for it (sized from the same budget,
  `backlog_messages`) then drops its oldest messages: a slow viewer loses frames, and costs a
  bounded amount, as foxglove_bridge's `send_buffer_limit` (10 MB by default) bounds it;
- the other direction (a viewer's subscriptions) is small and relayed as it comes;
- a viewer that asks for the protocol by its old name, `foxglove.websocket.v1` (Lichtblick, Foxglove
  builds before the SDK), is served: foxglove-sdk speaks only `foxglove.sdk.v1` and answered it HTTP 400,
  though the two are the same protocol renamed (Foxglove's word, foxglove/ros-foxglove-bridge#382). The
  gate renames it in the viewer's upgrade request, and back in the server's answer; after the
  handshake the bytes pass as they come.
"""
from __future__ import annotations

import logging
import selectors
import socket
import threading
import time

log = logging.getLogger("tecdar.viz")

CHUNK_BYTES = 64 * 1024
LARGEST_MESSAGE_BYTES = 32 * 1024      # a 20 ms IMU batch as JSON is ~17 kB; the server's queue is in messages
REFUSED = b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
REFUSE_WAIT_S = 2.0                    # a turned-away client's request is waited for this long
MAX_REFUSING = 64                      # turned-away clients waited for at once; more are closed at once


def backlog_messages(buffer_bytes: int) -> int:
    """foxglove-sdk's per-client queue, in messages, for a per-viewer budget in bytes."""
    return max(8, buffer_bytes // LARGEST_MESSAGE_BYTES)


OLD_NAME, SDK_NAME = b"foxglove.websocket.v1", b"foxglove.sdk.v1"
MAX_HEAD_BYTES = 16 * 1024             # an upgrade request's or answer's headers; longer: no viewer of ours


def rename_offer(head: bytes) -> tuple[bytes, bool]:
    """A viewer's upgrade request with the old name of the protocol offered as the SDK's (where it does not
    offer the SDK's itself), and whether it was renamed."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            offered = [v.strip() for v in value.split(b",")]
            if OLD_NAME in offered and SDK_NAME not in offered:
                lines[i] = name + b": " + b", ".join(SDK_NAME if v == OLD_NAME else v for v in offered)
                return b"\r\n".join(lines), True
    return head, False


def rename_answer(head: bytes) -> bytes:
    """The server's answer to a renamed offer, with the name the viewer asked for."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol" and value.strip() == SDK_NAME:
            lines[i] = name + b": " + OLD_NAME
    return b"\r\n".join(lines)


class _Pair:
    """A viewer's connection and the relay's connection to the server for it."""

    def __init__(self, viewer: socket.socket, upstream: socket.socket):
        self.viewer, self.upstream = viewer, upstream
        self.to_viewer = bytearray()          # from the server, waiting for the viewer to read
        self.to_upstream = bytearray()        # from the viewer, waiting for the server
        self.request: bytearray | None = bytearray()    # the viewer's upgrade request until it is whole
        self.answer: bytearray | None = None            # the server's answer, held while a renamed offer's
        self.renamed = False

    def handshake(self, data: bytes, from_viewer: bool) -> bytes | None:
        """`data` as it is to be relayed: the headers renamed once whole (None: not whole yet, held)."""
        held = self.request if from_viewer else self.answer
        if held is None:
            return data
        held += data
        end = held.find(b"\r\n\r\n")
        if end < 0:
            if len(held) > MAX_HEAD_BYTES:
                raise OSError("an upgrade's headers longer than any viewer's")
            return None
        head, rest = bytes(held[:end]), bytes(held[end:])
        if from_viewer:
            self.request = None
            head, self.renamed = rename_offer(head)
            self.answer = bytearray() if self.renamed else None
        else:
            self.answer = None
            head = rename_answer(head)
        return head + rest


class ViewerGate:
    """Listens on (host, port) and relays each accepted viewer to the server at `upstream_port`."""

    def __init__(self, host: str, port: int, upstream_port: int, max_viewers: int, buffer_bytes: int):
        self.upstream = ("127.0.0.1", upstream_port)
        self.max_viewers, self.buffer_bytes = max_viewers, buffer_bytes
        self.listener = socket.create_server((host, port), reuse_port=False)
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.refused = 0                      # connections turned away at the cap
        self.viewers = 0
        self._sel = selectors.DefaultSelector()
        self._pairs: dict[socket.socket, _Pair] = {}
        self._refusing: dict[socket.socket, float] = {}     # turned away, answered once their request is in

    def run(self, stop: threading.Event) -> None:
        self._sel.register(self.listener, selectors.EVENT_READ)
        try:
            while not stop.is_set():
                for key, mask in self._sel.select(0.1):
                    if key.fileobj is self.listener:
                        self._accept()
                    elif key.fileobj in self._refusing:
                        self._refuse(key.fileobj)
                    else:
                        self._service(key.fileobj, mask)
                now = time.monotonic()
                for s in [s for s, by in self._refusing.items() if by < now]:
                    self._refuse(s, answer=False)
        finally:
            for pair in list(self._pairs.values()):
                self._close(pair)
            for s in list(self._refusing):
                self._refuse(s, answer=False)
            self._sel.close()
            self.listener.close()

    def _accept(self) -> None:
        try:
            viewer, _ = self.listener.accept()
        except OSError:
            return
        if self.viewers >= self.max_viewers:
            self.refused += 1
            if self.refused == 1 or self.refused % 100 == 0:
                log.warning("live view: a viewer turned away, %d are connected (viz.foxglove.max_viewers); "
                            "%d turned away so far", self.viewers, self.refused)
            if len(self._refusing) >= MAX_REFUSING:
                viewer.close()
                return
            viewer.setblocking(False)           # answered once its request is in (a client that has not
            self._refusing[viewer] = time.monotonic() + REFUSE_WAIT_S      # sent it yet would miss the answer)
            self._sel.register(viewer, selectors.EVENT_READ)
            return
        try:
            upstream = socket.create_connection(self.upstream, timeout=2.0)
        except OSError as exc:
            log.warning("live view: its server did not answer (%s)", exc)
            viewer.close()
            return
        for s in (viewer, upstream):
            s.setblocking(False)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        pair = _Pair(viewer, upstream)
        self._pairs[viewer] = self._pairs[upstream] = pair
        self.viewers += 1
        self._update(pair)

    def _refuse(self, s: socket.socket, answer: bool = True) -> None:
        self._refusing.pop(s, None)
        try:
            self._sel.unregister(s)
        except (KeyError, ValueError):
            pass
        try:
            if answer:
                s.recv(CHUNK_BYTES)
                s.send(REFUSED)
                s.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        s.close()

    def _update(self, pair: _Pair) -> None:
        """What each side is watched for: read while the other side's waiting bytes are under budget,
        write while there are bytes for it."""
        want = {pair.viewer: (len(pair.to_upstream) < CHUNK_BYTES, bool(pair.to_viewer)),
                pair.upstream: (len(pair.to_viewer) < self.buffer_bytes, bool(pair.to_upstream))}
        for s, (read, write) in want.items():
            mask = (selectors.EVENT_READ if read else 0) | (selectors.EVENT_WRITE if write else 0)
            try:
                if mask:
                    try:
                        self._sel.modify(s, mask)
                    except KeyError:
                        self._sel.register(s, mask)
                else:
                    self._sel.unregister(s)
            except (KeyError, ValueError):
                pass

    def _service(self, s: socket.socket, mask: int) -> None:
        pair = self._pairs.get(s)
        if pair is None:
            return
        from_viewer = s is pair.viewer
        out, peer = (pair.to_upstream, pair.upstream) if from_viewer else (pair.to_viewer, pair.viewer)
        inbox = pair.to_viewer if from_viewer else pair.to_upstream      # what waits to be written to s
        try:
            if mask & selectors.EVENT_READ:
                data = s.recv(CHUNK_BYTES)
                if not data:
                    self._close(pair)
                    return
                data = pair.handshake(data, from_viewer)
                if data is not None:
                    out += data
                    self._flush(out, peer)
            if mask & selectors.EVENT_WRITE:
                self._flush(inbox, s)
        except OSError:
            self._close(pair)
            return
        self._update(pair)

    @staticmethod
    def _flush(buf: bytearray, s: socket.socket) -> None:
        if buf:
            try:
                sent = s.send(buf)
            except BlockingIOError:
                return
            del buf[:sent]

    def _close(self, pair: _Pair) -> None:
        if self._pairs.pop(pair.viewer, None) is None:
            return                                 # closed already
        self._pairs.pop(pair.upstream, None)
        self.viewers -= 1
        for s in (pair.viewer, pair.upstream):
            try:
                self._sel.unregister(s)
            except (KeyError, ValueError):
                pass
            s.close()
