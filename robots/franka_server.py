"""The Franka robot server's Connect handshake (port 1337), read before franky connects: which robot server
version the robot speaks, and whether it is the one this franky speaks (robots/franka_link.py, and
`tecdard doctor`'s check in robots/franka.py)."""
from __future__ import annotations

import socket
import struct
import time

LIBFRANKA_ROBOT_SERVER_VERSION = 10     # the robot server version franky 2.0 (libfranka 0.21.2) speaks
ROBOT_PORT = 1337                       # the FCI's robot server (the hand's is 1338)
CONNECT_COMMAND = 0                     # libfranka's research interface: Command::kConnect
CONNECT_HEADER_BYTES = 12
CONNECT_INCOMPATIBLE = 1                # Connect::Status::kIncompatibleLibraryVersion


def server_version(host: str, timeout_s: float) -> tuple[int, int]:
    """(status, version) of the robot server's answer to libfranka's Connect on port 1337, read
    before franky connects, because libfranka 0.21 checks no version when the server says success:
    a robot of another system version would be driven with a state layout it does not send.

    The request is libfranka's: a header (uint32 command 0, id, message size) and the library's
    version and a UDP port (uint16 each). libfranka's reply is packed: status (uint8), version
    (uint16), 3 bytes. franky-sim 1.0.4 answers 8 bytes (uint16 status, uint16 version, padding),
    so the reply's length says which layout it has. Raises OSError (nothing listening, or no
    answer within timeout_s) or ValueError (an answer that is no Connect reply)."""
    deadline = time.monotonic() + timeout_s
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        udp.bind(("", 0))
        with socket.create_connection((host, ROBOT_PORT), timeout=timeout_s) as sock:
            sock.sendall(struct.pack("<III", CONNECT_COMMAND, 1, CONNECT_HEADER_BYTES + 4)
                         + struct.pack("<HH", LIBFRANKA_ROBOT_SERVER_VERSION, udp.getsockname()[1]))
            data = b""
            size = None
            while size is None or len(data) < size:
                sock.settimeout(max(deadline - time.monotonic(), 1e-3))
                chunk = sock.recv(256)
                if not chunk:
                    raise ValueError(f"the server at {host} closed the connection without a Connect reply")
                data += chunk
                if size is None and len(data) >= CONNECT_HEADER_BYTES:
                    command, _, size = struct.unpack("<III", data[:CONNECT_HEADER_BYTES])
                    if command != CONNECT_COMMAND or not CONNECT_HEADER_BYTES + 3 <= size <= 64:
                        raise ValueError(f"the server at {host} gave no Connect reply (command {command}, "
                                         f"{size} bytes)")
    finally:
        udp.close()
    payload = data[CONNECT_HEADER_BYTES:size]
    if len(payload) >= 8:
        return struct.unpack("<HH", payload[:4])
    return payload[0], struct.unpack("<H", payload[1:3])[0]
