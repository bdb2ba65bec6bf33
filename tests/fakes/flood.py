"""A hostile local client for the whole-daemon tests: floods a daemon's cmd/ keys with queries.

    python -m tests.fakes.flood ENDPOINT SECONDS [ROBOT]

Sends what the red team sent: first 40 payloads of 10 MB to `status` (which the daemon's transport
drops unread), then, round after round until SECONDS have passed (at least one round), a burst of BURST concurrent
`status` queries with junk and oversized payloads on `status` and on unknown verbs among them.
It never waits for a reply. Prints how many queries it sent.
"""
from __future__ import annotations

import signal
import sys
import time

import zenoh

from tecdard.api.session import Keys, session_config

BURST = 12000                   # the red team's "12 000 concurrent status queries"
BIG = 40                        # 10 MB payloads at the start
PAUSE_S = 0.5
JUNK = [b"{", b"[" * 1000 + b"]" * 1000, b'{"angle_deg": ' + b"9" * 5000 + b"}", b"\xff\xfe",
        b'{"angle_deg": 1000}', b" " * 100_000, b'{"direction": [1e308, 1e308, 0]}']
BIG_PAYLOAD = b" " * 10_000_000


def main(argv: list[str]) -> int:
    endpoint, seconds = argv[0], float(argv[1])
    keys = Keys(argv[2] if len(argv) > 2 else "sim")
    sent = 0
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))     # ends the flood, then the count is printed
    with zenoh.open(session_config([], [endpoint])) as session:
        time.sleep(0.3)                        # the route to the daemon's queryables
        t_end = time.monotonic() + seconds
        for _ in range(BIG):
            session.get(keys.cmd("status"), payload=BIG_PAYLOAD, timeout=1.0)
            sent += 1
        first = True
        while first or (time.monotonic() < t_end and not stop):
            first = False
            for i in range(BURST):
                if stop:
                    break
                if i % 10:
                    session.get(keys.cmd("status"), timeout=1.0)
                else:
                    verb = ("status", "dance", "stop/now", "status")[i // 10 % 4]
                    session.get(keys.cmd(verb), payload=JUNK[i // 40 % len(JUNK)], timeout=1.0)
                sent += 1
            time.sleep(PAUSE_S)
    print(sent, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
