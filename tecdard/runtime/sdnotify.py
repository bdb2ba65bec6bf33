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
        self._stopping = False
        if path:
            self.addr = "\0" + path[1:] if path.startswith("@") else path
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self.sock is not None

    def notify(self, message: str) -> bool:
        """Sent, or False. Never waits: the control tick pings the watchdog, and a blocking send to a
        manager that has stopped reading (its queue full, net.unix.max_dgram_qlen: 10) holds the tick,
        and with it an orderly shutdown. A message that cannot be queued is dropped."""
        if self.sock is None:
            return False
        try:
            self.sock.sendto(message.encode(), socket.MSG_DONTWAIT, self.addr)
            return True
        except OSError:
            return False

    def stopping(self) -> None:
        """STOPPING=1, once: as the daemon's shutdown begins (the arm's stop, the last writes), not at
        its end."""
        if not self._stopping:
            self._stopping = True
            self.notify("STOPPING=1")

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
