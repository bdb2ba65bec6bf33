"""`tecdard fleet status` and `fleet watch`: one table of every robot that answers through the router,
from what each daemon publishes (its `state` and `contact` messages and its liveliness token), so that
an operator who may command no robot still sees the fleet."""
from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, field

from tecdard.api.session import DAEMON_NAME, TlsFiles, client_config
from tecdard.safejson import MAX_DEPTH, finite, json_ready, nesting_depth, show_name

STATE_FRESH_S = 1.0            # a robot whose last state is older than this is `silent` (states come at 50 Hz)
GATHER_S = 1.5                 # fleet status: how long it listens for the robots' states at most
LINK_FAULTS = ("robot_link", "robot_stale", "imu_disconnected", "imu_stale")
COLUMNS = ("robot", "mode", "task", "faults", "last contact (mm)", "IMU (Hz)", "overruns", "link")


@dataclass
class RobotSeen:
    """What one robot's daemon last published, as this client received it (monotonic s)."""
    state: dict | None = None
    state_at: float = float("-inf")
    contact: dict | None = None
    alive: bool = False
    faults_seen: set = field(default_factory=set)


class FleetView:
    """A Zenoh client of the router (client mode, no gossip; with TLS it takes what the node sends only
    if its certificate is named `router_name`) that keeps each robot's newest state and contact."""

    def __init__(self, endpoint: str, tls: TlsFiles | None = None, router_name: str = DAEMON_NAME,
                 robots: str = "*"):
        import zenoh
        from tecdard.api.client import direct_callback
        self.robots: dict[str, RobotSeen] = {}
        self._lock = threading.Lock()
        self.pattern = robots
        self.session = zenoh.open(client_config(endpoint, "*", tls, router_name, connect_timeout_s=2.0))
        self._subs = [self.session.declare_subscriber(f"tecdar/{robots}/state", direct_callback(self._on_state)),
                      self.session.declare_subscriber(f"tecdar/{robots}/contact", direct_callback(self._on_contact))]

    def _seen(self, sample) -> RobotSeen:
        robot = str(sample.key_expr).split("/")[1]
        with self._lock:
            return self.robots.setdefault(robot, RobotSeen())

    @staticmethod
    def _decoded(sample) -> dict | None:
        """A robot's message as an object, or None (not UTF-8, not JSON, nested too deep, not an object: that
        robot's row shows it silent, and the view goes on); NaN and the infinities read as null."""
        try:
            text = sample.payload.to_bytes().decode("utf-8")
            if nesting_depth(text) > MAX_DEPTH:
                return None
            value = json.loads(text, parse_constant=lambda _: None)      # NaN and the infinities: unknown
        except (ValueError, RecursionError):
            return None
        return value if isinstance(value, dict) else None

    def _on_state(self, sample) -> None:
        state = self._decoded(sample)
        if state is not None:
            seen = self._seen(sample)
            seen.state, seen.state_at = state, time.monotonic()

    def _on_contact(self, sample) -> None:
        contact = self._decoded(sample)
        if contact is not None:
            self._seen(sample).contact = contact

    def refresh_alive(self, timeout_s: float = 0.5) -> None:
        """Which robots hold their liveliness token now."""
        alive = set()
        for reply in self.session.liveliness().get(f"tecdar/{self.pattern}/alive", timeout=timeout_s):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 3:
                    alive.add(parts[1])
        with self._lock:
            for name in alive:
                self.robots.setdefault(name, RobotSeen())
            for name, seen in self.robots.items():
                seen.alive = name in alive

    def gather(self, window_s: float = GATHER_S) -> None:
        """Listen until every robot alive has sent a state, or window_s."""
        deadline = time.monotonic() + window_s
        self.refresh_alive(min(0.5, window_s))
        while time.monotonic() < deadline:
            with self._lock:
                waiting = [s for s in self.robots.values() if s.alive and s.state is None]
            if not waiting:
                break
            time.sleep(0.05)

    def rows(self) -> list[dict]:
        """One row per robot seen, by name: SI and the table's own units side by side."""
        now = time.monotonic()
        with self._lock:
            items = sorted(self.robots.items())
        return [row(name, seen, now) for name, seen in items]

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.session.close()


BAD = "?"                      # a field a robot sent malformed: shown as such in its row only
MODES = ("idle", "busy", "stopped", "fault")


def _text(x, limit: int = 48) -> str:
    """A robot's string as a cell: escaped (no control character reaches the terminal), cut to `limit`; BAD for
    anything but a string."""
    return show_name(x, limit) if isinstance(x, str) else BAD


def _count(x):
    return x if isinstance(x, int) and not isinstance(x, bool) and x >= 0 else BAD


def row(name: str, seen: RobotSeen, now: float) -> dict:
    """A robot's row: mode, task, fault codes, the newest contact estimate (m), the IMU rate (Hz), the
    control tick's overruns and the link: ok, silent (alive, no state for STATE_FRESH_S), gone (no
    token), or the fault that says the robot or the board cannot be reached. Each field is read on its own:
    one a robot sent malformed is BAD in its row (its name in `bad`), the rest of the row and the fleet stand;
    non-finite numbers are None."""
    s = seen.state if isinstance(seen.state, dict) else {}
    bad: list[str] = []

    def check(key: str, value):
        if value == BAD:
            bad.append(key)
        return value
    mode = s.get("mode")
    mode = None if mode is None else check("mode", mode if mode in MODES else BAD)
    raw_faults = s.get("faults") or []
    faults = [check("faults", _text(f.get("code")) if isinstance(f, dict) else BAD)
              for f in (raw_faults if isinstance(raw_faults, list) else [None])]
    task = s.get("task")
    if task is not None:
        task = check("task", {"kind": _text(task.get("kind")), "phase": _text(task.get("phase"))}
                     if isinstance(task, dict) and isinstance(task.get("kind"), str)
                     and isinstance(task.get("phase"), str) else BAD)
    contact = s.get("contact") or seen.contact
    p = contact.get("p") if isinstance(contact, dict) else None
    contact_p = None if p is None else check("contact", [finite(x) for x in p] if isinstance(p, list) and len(p) == 3
                                             and all(finite(x) is not None for x in p) else BAD)
    imu = s.get("imu")
    rate = imu.get("rate_hz") if isinstance(imu, dict) else (BAD if imu is not None else None)
    rate = None if rate is None else check("imu", finite(rate) if finite(rate) is not None else BAD)
    lost = imu.get("lost_s") if isinstance(imu, dict) else None
    lost = None if lost is None else check("imu", finite(lost) if finite(lost) is not None else BAD)
    control = s.get("control")
    overruns = control.get("overruns") if isinstance(control, dict) else (BAD if control is not None else None)
    overruns = None if overruns is None else check("overruns", _count(overruns))
    age = now - seen.state_at
    link_fault = next((c for c in LINK_FAULTS if c in faults), None)     # the cause before its effect (stale)
    if not seen.alive:
        link = "gone"
    elif seen.state is None or age > STATE_FRESH_S:
        link = "silent"
    else:
        link = link_fault or "ok"
        if link == "imu_disconnected" and lost is not None and lost != BAD:
            link = f"imu_disconnected {lost:.0f} s"        # how long the board has been gone
    return {"robot": _text(name), "mode": mode, "task": task, "faults": faults, "contact_p": contact_p,
            "imu_rate_hz": rate, "imu_lost_s": lost, "overruns": overruns, "link": link,
            "state_age_s": None if seen.state is None else round(age, 3), "bad": sorted(set(bad))}


def table(rows: list[dict]) -> str:
    """The rows as a text table, the contact in mm; a malformed field as `?`."""
    def cells(r):
        task, p = r["task"], r["contact_p"]
        return (r["robot"], r["mode"] or "-",
                "-" if task is None else BAD if task == BAD else f"{task['kind']} {task['phase']}",
                ",".join(r["faults"]) or "-",
                "-" if p is None else BAD if p == BAD else "(" + ", ".join(f"{1e3 * x:.1f}" for x in p) + ")",
                "-" if r["imu_rate_hz"] is None else BAD if r["imu_rate_hz"] == BAD else f"{r['imu_rate_hz']:.0f}",
                "-" if r["overruns"] is None else str(r["overruns"]), r["link"])
    lines = [COLUMNS] + [cells(r) for r in rows]
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(COLUMNS))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(line, widths)).rstrip() for line in lines)


def json_rows(rows: list[dict]) -> list:
    """The rows as strict JSON takes them: a malformed field as null (its name in `bad`), no NaN or infinity."""
    def nulls(x):
        if isinstance(x, dict):
            return {k: nulls(v) for k, v in x.items()}
        if isinstance(x, list):
            return [nulls(v) for v in x]
        return None if x == BAD else x
    return json_ready([{k: v if k == "bad" else nulls(v) for k, v in r.items()} for r in rows])


def run_status(args, watch: bool) -> int:
    from tecdard.api.session import endpoint_problem
    from tecdard.cli.task_verbs import EXIT_DONE, EXIT_NO_DAEMON, EXIT_REFUSED, tls_files
    from tecdard.safejson import first_line
    problem = endpoint_problem(args.connect)
    if problem:
        print(f"tecdard fleet: --connect {args.connect}: {problem}", file=sys.stderr)
        return EXIT_REFUSED
    tls, problem = tls_files(args)
    if problem:
        print(f"tecdard fleet: {problem}", file=sys.stderr)
        return EXIT_REFUSED
    try:
        view = FleetView(args.connect, tls, args.tls_daemon_name, args.robot)
    except Exception as exc:              # zenoh.ZError: nothing there, a certificate refused
        print(f"tecdard fleet: cannot reach the router at {args.connect}: {first_line(exc)}", file=sys.stderr)
        return EXIT_NO_DAEMON
    try:
        if not watch:
            view.gather(args.wait)
            rows = view.rows()
            if args.json:
                print(json.dumps(json_rows(rows), allow_nan=False))
            else:
                print(table(rows) if rows else f"no robot answers at {args.connect}")
            return EXIT_DONE if rows else EXIT_NO_DAEMON
        tty = sys.stdout.isatty()
        view.gather(GATHER_S)            # the first table with every robot's state, as `status` shows it
        while True:
            view.refresh_alive(0.5)
            rows = view.rows()
            if args.json:
                print(json.dumps({"t": time.time(), "robots": json_rows(rows)}, allow_nan=False), flush=True)
            else:
                text = table(rows) if rows else f"no robot answers at {args.connect}"
                print(("\033[H\033[J" if tty else "") + time.strftime("%H:%M:%S ") + args.connect + "\n" + text + "\n",
                      flush=True)
            time.sleep(args.period)
    except KeyboardInterrupt:
        return EXIT_DONE
    finally:
        view.close()
