"""A Robotiq 2F-85/140 behind its URCap's socket, for the tests: written from Robotiq's manual, not from a client.

The URCap on a UR controller serves the gripper on port 63352: one ASCII command a line. `SET <VAR> <n>`, with
one or more variable-value pairs, is answered `ack`; `GET <VAR>` is answered `<VAR> <n>`; anything else `?`.
The variables are the gripper's registers (the manual's "Control" chapter):

- written: ACT (1 activates; 0 resets), GTO (1 goes to the request, 0 stops), POS (the position request,
  0 open .. 255 closed), SPE and FOR (speed and force requests, 0..255), ATR (automatic release, unused here);
- read: STA (0 reset, 1 activating, 3 activated), PRE (the position request echoed), POS (the fingers'
  position), OBJ (0 moving, 1 stopped opening on an object, 2 stopped closing on an object, 3 at the
  request, nothing met), FLT (0 none; 0x05 an action before activation completed).

The fingers move at the speed request (20..150 mm/s on a 2F-85, over its 85 mm stroke) and stop at the
request, or where they meet the object (`object_width_m`, None for an empty hand) while closing. Activation
takes `activate_s`. It binds its own 127.0.0.x (the port is fixed, as the URCap's is) and serves one client
at a time, as many in turn as come.
"""
from __future__ import annotations

import socket
import threading
import time

PORT = 63352
STROKE_M = {"2f-85": 0.085, "2f-140": 0.140}
SPEED_M_S = {"2f-85": (0.020, 0.150), "2f-140": (0.030, 0.250)}
WRITABLE = ("ACT", "GTO", "POS", "SPE", "FOR", "ATR", "ADR")
READABLE = ("ACT", "GTO", "STA", "PRE", "POS", "OBJ", "FLT", "SPE", "FOR")


class FakeUrcap:
    def __init__(self, host: str, model: str = "2f-85", object_width_m: float | None = 0.025,
                 activate_s: float = 0.2, activated: bool = False, port: int = PORT):
        self.host, self.port, self.model = host, port, model
        self.object_width_m = object_width_m
        self.activate_s = activate_s
        self.lock = threading.Lock()
        self.reg = {"ACT": 0, "GTO": 0, "STA": 0, "PRE": 0, "POS": 0, "OBJ": 3, "FLT": 0, "SPE": 255, "FOR": 150}
        self.pos = 0.0                    # the fingers, in position counts (float between updates)
        self.activated_at: float | None = None
        if activated:
            self.reg.update(ACT=1, STA=3)
        self.commands: list[str] = []     # every line received, for the tests
        self.last_t = time.monotonic()
        self.server = socket.create_server((host, port))
        self.server.settimeout(0.2)
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="fake-urcap", daemon=True)
        self.thread.start()

    # -- the gripper --------------------------------------------------------------------------------
    def _contact_count(self) -> float | None:
        if self.object_width_m is None:
            return None
        return 255.0 * (1.0 - self.object_width_m / STROKE_M[self.model])

    def _advance(self, now: float) -> None:
        """Time passes: activation completes, the fingers move toward the request, or stop on the object."""
        dt, self.last_t = now - self.last_t, now
        r = self.reg
        if r["STA"] == 1 and self.activated_at is not None and now - self.activated_at >= self.activate_s:
            r["STA"] = 3
        if r["STA"] != 3 or r["GTO"] != 1 or r["OBJ"] != 0:
            return
        lo, hi = SPEED_M_S[self.model]
        rate = (lo + (hi - lo) * r["SPE"] / 255.0) / STROKE_M[self.model] * 255.0      # counts per second
        target = float(r["PRE"])
        contact = self._contact_count()
        step = rate * dt
        if self.pos < target:                                                         # closing
            stop_at = target if contact is None or contact > target else contact
            self.pos = min(self.pos + step, stop_at)
            if self.pos >= stop_at:
                r["OBJ"] = 2 if stop_at < target else 3
        else:                                                                          # opening
            self.pos = max(self.pos - step, target)
            if self.pos <= target:
                r["OBJ"] = 3
        r["POS"] = int(round(self.pos))

    def set_object(self, width_m: float | None) -> None:
        with self.lock:
            self.object_width_m = width_m

    # -- the socket ---------------------------------------------------------------------------------
    def _answer(self, line: str) -> str:
        words = line.split()
        with self.lock:
            now = time.monotonic()
            self._advance(now)
            self.commands.append(line)
            if len(words) == 2 and words[0] == "GET" and words[1] in READABLE:
                return f"{words[1]} {self.reg[words[1]]}"
            if len(words) >= 3 and words[0] == "SET" and len(words) % 2 == 1:
                pairs = list(zip(words[1::2], words[2::2]))
                if not all(k in WRITABLE and v.isdigit() and 0 <= int(v) <= 255 for k, v in pairs):
                    return "?"
                for k, v in pairs:
                    self._write(k, int(v), now)
                return "ack"
            return "?"

    def _write(self, reg: str, value: int, now: float) -> None:
        r = self.reg
        if reg == "ACT":
            r["ACT"] = value
            if value == 1 and r["STA"] != 3:
                r["STA"], self.activated_at, r["FLT"] = 1, now, 0
            elif value == 0:
                r.update(STA=0, GTO=0, OBJ=3)
        elif reg == "GTO":
            if value == 1 and r["STA"] != 3:
                r["FLT"] = 0x05          # an action before activation completed
                return
            r["GTO"] = value
            if value == 1:
                target = r["PRE"]
                r["OBJ"] = 3 if abs(self.pos - target) < 0.5 else 0
        elif reg == "POS":
            r["PRE"] = value
            if r["GTO"] == 1 and r["STA"] == 3:
                r["OBJ"] = 3 if abs(self.pos - value) < 0.5 else 0
        else:
            r[reg] = value

    def _serve(self) -> None:
        while not self.closing.is_set():
            try:
                conn, _ = self.server.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(0.2)
                buf = b""
                while not self.closing.is_set():
                    try:
                        chunk = conn.recv(256)
                    except (TimeoutError, socket.timeout):
                        continue
                    except OSError:
                        break
                    if not chunk:
                        break
                    buf += chunk
                    while b"\n" in buf:
                        line, _, buf = buf.partition(b"\n")
                        try:
                            conn.sendall((self._answer(line.decode("ascii", "replace").strip()) + "\n").encode())
                        except OSError:
                            break

    def close(self) -> None:
        self.closing.set()
        self.server.close()
        self.thread.join(timeout=2.0)


def free_urcap_host() -> str:
    """A 127.0.0.x address whose port 63352 is free."""
    import random
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        try:
            with socket.create_server((host, PORT)):
                return host
        except OSError:
            continue
    raise RuntimeError("no free 127.0.0.x address for the Robotiq URCap fake")
