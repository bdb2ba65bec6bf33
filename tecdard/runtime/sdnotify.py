"""systemd notify protocol (READY=1, WATCHDOG=1, STOPPING=1) written to $NOTIFY_SOCKET directly."""
from __future__ import annotations

import os
import socket


class Notifier:
    """No-op when not started by systemd (no NOTIFY_SOCKET)."""

    def __init__(self, path: str | None = None):
        path = path if path is not None else os.environ.get("NOTIFY_SOCKET")
        self.addr = None
        self.sock = None
        if path:
            self.addr = "\0" + path[1:] if path.startswith("@") else path
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self.sock is not None

    def notify(self, message: str) -> bool:
        if self.sock is None:
            return False
        try:
            self.sock.sendto(message.encode(), self.addr)
            return True
        except OSError:
            return False

    def watchdog_interval_s(self) -> float | None:
        """Half of WATCHDOG_USEC when the watchdog is on for this process, else None."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec or (pid and pid != str(os.getpid())):
            return None
        try:
            return int(usec) / 2e6
        except ValueError:
            return None
