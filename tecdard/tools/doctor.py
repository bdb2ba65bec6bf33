"""`tecdard doctor`: is this host ready to run the daemon beside a real arm?

One line per check, PASS, WARN, FAIL or SKIP, with the fix under anything that is not a pass;
the exit status is 1 when any check fails. A warning is something the daemon runs with but an
operator should know (a kernel that is not real-time, a CPU governor that scales down); a failure
is something `tecdard run` would refuse or that leaves the daemon without its data (the config, the
board, the endpoint).

Every check reads the host through arguments with the real defaults, so the tests can point them
at a scratch directory.
"""
from __future__ import annotations

import glob
import grp
import os
import pathlib
import platform
import pwd
import socket
from dataclasses import dataclass

ROOT = pathlib.Path(__file__).resolve().parents[2]
UDEV_RULE = ROOT / "systemd" / "99-tecdar-imu.rules"
UDEV_RULE_DIRS = ("/etc/udev/rules.d", "/run/udev/rules.d", "/usr/lib/udev/rules.d", "/lib/udev/rules.d")
DEFAULT_RT_PRIORITY = 80      # what the doctor tries when the config names none
CONNECT_TIMEOUT_S = 1.0


@dataclass(frozen=True)
class Check:
    name: str
    status: str               # pass | warn | fail | skip
    detail: str
    fix: str | None = None

    def lines(self) -> list[str]:
        out = [f"{self.status.upper():4}  {self.name}: {self.detail}"]
        if self.fix and self.status != "pass":
            out.append(f"      fix: {self.fix}")
        return out


# -- the host ------------------------------------------------------------------
def check_rt_kernel(sys_realtime: str = "/sys/kernel/realtime", version: str | None = None) -> Check:
    version = platform.uname().version if version is None else version
    try:
        flag = pathlib.Path(sys_realtime).read_text().strip() == "1"
    except OSError:
        flag = False
    if flag or "PREEMPT_RT" in version:
        return Check("real-time kernel", "pass", f"PREEMPT_RT ({version[:60]})")
    return Check("real-time kernel", "warn", f"not PREEMPT_RT ({version[:60]}): a 20 ms tick can be late "
                 "by milliseconds under load",
                 "boot a real-time kernel (Debian: linux-image-rt-amd64; Ubuntu: `pro enable realtime-kernel`)")


def check_rtprio(priority: int | None) -> Check:
    from tecdard.runtime.realtime import can_set_fifo, rtprio_limit
    asked = priority is not None
    prio = priority if asked else DEFAULT_RT_PRIORITY
    soft, hard = rtprio_limit()
    problem = can_set_fifo(prio)
    source = "control.rt_priority" if asked else f"no control.rt_priority set; tried {prio}"
    if problem is None:
        return Check("SCHED_FIFO", "pass", f"priority {prio} ({source}) can be set here; RLIMIT_RTPRIO {soft}/{hard}"
                     + ("" if soft >= prio else " (allowed by CAP_SYS_NICE)"))
    return Check("SCHED_FIFO", "warn", f"priority {prio} ({source}): {problem}",
                 "the unit's LimitRTPRIO= (systemd/tecdard.service), or `@tecdar - rtprio 80` in "
                 "/etc/security/limits.d/tecdar.conf for a login session")


def check_governor(cpu_glob: str = "/sys/devices/system/cpu/cpu[0-9]*/cpufreq/scaling_governor") -> Check:
    found = {}
    for path in sorted(glob.glob(cpu_glob)):
        try:
            found[path] = pathlib.Path(path).read_text().strip()
        except OSError:
            continue
    fix = "`sudo cpupower frequency-set -g performance` (and make it persist: cpufrequtils or a tuned profile)"
    if not found:
        return Check("CPU governor", "warn", "no cpufreq governor exposed (a VM or a container?): the host's own "
                     "frequency scaling applies", fix)
    others = sorted({g for g in found.values() if g != "performance"})
    if not others:
        return Check("CPU governor", "pass", f"performance on all {len(found)} CPUs")
    return Check("CPU governor", "warn", f"{', '.join(others)} on {sum(g != 'performance' for g in found.values())} "
                 f"of {len(found)} CPUs: waking from a low clock adds latency to each tick", fix)


# -- the fingertip board ---------------------------------------------------------
def _access_problem(path: str) -> tuple[str, str] | None:
    """None, or (what is wrong, the device's group)."""
    if os.access(path, os.R_OK | os.W_OK):
        return None
    st = os.stat(path)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    user = pwd.getpwuid(os.getuid()).pw_name
    return f"{path} is mode {st.st_mode & 0o777:o}, group {group}, and {user} may not read and write it", group


def check_board(serial_params, comports=None) -> Check:
    """The board at its configured port (by path, or found by VID:PID) and readable and writable."""
    if serial_params is None:
        return Check("fingertip board", "skip", "imu.source is not serial (the simulated board is used)")
    from tecdard.drivers.serial_imu import PortError, find_port
    if comports is None:
        import serial.tools.list_ports
        comports = serial.tools.list_ports.comports
    p = serial_params
    if p.port is not None:
        path = p.port
        if not os.path.exists(path):
            fix = ("plug the board in; with the udev rule installed it appears as /dev/tecdar-imu"
                   if "tecdar-imu" in path else "plug the board in, or correct imu.serial.port")
            return Check("fingertip board", "fail", f"{path} does not exist", fix)
    else:
        try:
            path = find_port(p.vid, p.pid, p.serial_number, comports)
        except PortError as exc:
            seen = ", ".join(f"{i.device} {i.vid:04x}:{i.pid:04x}" for i in comports() if i.vid is not None)
            return Check("fingertip board", "fail", f"{exc}" + (f" (connected: {seen})" if seen else ""),
                         "plug the board in, or correct imu.serial.vid_pid (`lsusb` lists the IDs)")
    problem = _access_problem(path)
    if problem is not None:
        detail, group = problem
        return Check("fingertip board", "fail", detail,
                     f"`sudo usermod -aG {group} $USER` and log in again (the unit runs with "
                     f"SupplementaryGroups={group}); the udev rule sets the group")
    return Check("fingertip board", "pass", f"{path} (real path {os.path.realpath(path)}) readable and writable")


def check_udev_rule(dirs=UDEV_RULE_DIRS, rule: pathlib.Path = UDEV_RULE) -> Check:
    fix = (f"sudo install -m 644 {rule} /etc/udev/rules.d/ && sudo udevadm control --reload && "
           "sudo udevadm trigger --subsystem-match=tty")
    ours = rule.read_text()
    for d in dirs:
        path = pathlib.Path(d) / rule.name
        if path.exists():
            try:
                same = path.read_text() == ours
            except OSError:
                same = False
            if same:
                return Check("udev rule", "pass", f"{path}")
            return Check("udev rule", "warn", f"{path} differs from {rule} (edited for another board?)", fix)
    return Check("udev rule", "warn", f"{rule.name} not installed: the board is /dev/ttyACM<n>, which can change "
                 "between plugs, and ModemManager may probe it", fix)


# -- the daemon's own ---------------------------------------------------------------
def _host_port(endpoint: str) -> tuple[str, str, int] | None:
    proto, _, addr = endpoint.partition("/")
    host, sep, port = addr.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return proto, host.strip("[]"), int(port)


def _daemon_alive_at(endpoint: str, robot: str, tls) -> bool:
    try:
        from tecdard.cli.client import Client
        with Client(endpoint, robot=robot, tls=tls, open_timeout_s=CONNECT_TIMEOUT_S) as cli:
            return cli.alive(CONNECT_TIMEOUT_S)
    except Exception:
        return False


def check_endpoints(listen: list[str], connect: list[str], robot: str = "sim", tls=None) -> list[Check]:
    out = []
    for ep in listen:
        hp = _host_port(ep)
        if hp is None or hp[0] not in ("tcp", "tls", "udp", "quic"):
            out.append(Check(f"zenoh.listen {ep}", "skip", "not a host:port endpoint; Zenoh checks it at start"))
            continue
        proto, host, port = hp
        kind = socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            with socket.socket(family, kind) as s:
                s.bind((host, port))
            out.append(Check(f"zenoh.listen {ep}", "pass", "free"))
        except OSError as exc:
            if _daemon_alive_at(ep, robot, tls):
                out.append(Check(f"zenoh.listen {ep}", "pass", f"in use by a running tecdard (tecdar/{robot}/alive)"))
            else:
                router = " (7447 is Zenoh's router port: zenohd, rmw_zenohd)" if port == 7447 else ""
                out.append(Check(f"zenoh.listen {ep}", "fail", f"cannot listen: {exc.strerror or exc}{router}",
                                 "pick a free port for zenoh.listen, or run through the router: zenoh.mode "
                                 "client and the router in zenoh.connect"))
    for ep in connect:
        hp = _host_port(ep)
        if hp is None or hp[0] not in ("tcp", "tls"):
            out.append(Check(f"zenoh.connect {ep}", "skip", "not a TCP endpoint; Zenoh checks it at start"))
            continue
        _, host, port = hp
        try:
            with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
                pass
            out.append(Check(f"zenoh.connect {ep}", "pass", "reachable"))
        except OSError as exc:
            out.append(Check(f"zenoh.connect {ep}", "fail", f"unreachable: {exc.strerror or exc}",
                             "start the router (zenohd) there, or correct zenoh.connect"))
    return out


def check_kernel_cache() -> Check:
    from tecdard.tools import kernel_cache
    try:
        state = kernel_cache.state()
    except Exception as exc:
        return Check("compiled-code cache", "warn", f"cannot tell: {exc}")
    if state.warm:
        return Check("compiled-code cache", "pass", state.describe())
    return Check("compiled-code cache", "warn", state.describe(),
                 "`tecdard warm` as the daemon's user, with the NUMBA_CACHE_DIR the daemon runs with "
                 "(the unit's: /var/cache/tecdar)")


def check_ur_controller(host: str, model: str) -> list[Check]:
    """A UR controller at `host`: its dashboard, RTDE and script ports answer, it runs the arm
    robot.model names, and it is in remote control (ur-rtde uploads its script only then)."""
    from tecdard.robots.ur_link import controller_identity
    from tecdard.robots.ur import expected_controller_arm
    ports = {"dashboard": 29999, "script": 30003, "RTDE": 30004}
    closed = []
    for name, port in ports.items():
        try:
            with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
                pass
        except OSError as exc:
            closed.append(f"{name} {port}: {exc.strerror or exc}")
    if closed:
        return [Check(f"UR controller {host}", "fail", "; ".join(closed),
                      "check robot.ur.host, the network to the controller, and that it is switched on")]
    out = [Check(f"UR controller {host}", "pass", "dashboard, script and RTDE ports answer")]
    identity = controller_identity(host)
    if not identity:
        out.append(Check("UR arm", "warn", "the dashboard did not say which arm this is",
                         f"check that robot.model {model} is the controller's arm"))
    else:
        theirs = expected_controller_arm(identity)
        ok = theirs.lower() == model
        out.append(Check("UR arm", "pass" if ok else "fail", f"{theirs}, software {identity['version']}",
                         None if ok else f"set robot.model: {theirs.lower()}"))
        if identity.get("remote_control") is False:
            out.append(Check("UR remote control", "fail", "the controller is in local control",
                             "switch the pendant to remote control (e-Series: the icon at its top right)"))
    return out


LIBFRANKA_RT_PRIORITY = 99           # libfranka puts its 1 kHz loop at SCHED_FIFO's highest priority
LIBFRANKA_MEMLOCK_BYTES = 100 << 20  # Franka's setup guide: `memlock 102400` (KiB) beside `rtprio 99`


def check_franka_realtime(realtime: str, sys_realtime: str = "/sys/kernel/realtime", version: str | None = None,
                          memlock: tuple[int, int] | None = None) -> list[Check]:
    """Whether this host is fit for robot.franka.realtime: enforce. libfranka then refuses to
    connect without a real-time kernel (franky's RealtimeException), raises its control thread to
    SCHED_FIFO 99 and locks its memory; a real arm stops with communication_constraints_violation
    when its 1 kHz packets come late."""
    import resource
    if realtime != "enforce":
        return [Check("Franka realtime", "warn", "robot.franka.realtime: ignore: libfranka's 1 kHz loop runs "
                      "without real-time priority; right for franky-sim, not for a real arm",
                      "set realtime: enforce beside a real arm, on a host this doctor passes")]
    kernel = check_rt_kernel(sys_realtime, version)
    out = [Check("Franka realtime kernel", "pass" if kernel.status == "pass" else "fail",
                 kernel.detail + ("" if kernel.status == "pass" else ": franky refuses to connect with realtime: "
                                  "enforce (RealtimeException)"), kernel.fix)]
    from tecdard.runtime.realtime import can_set_fifo
    problem = can_set_fifo(LIBFRANKA_RT_PRIORITY)
    out.append(Check("Franka SCHED_FIFO 99", "pass" if problem is None else "fail",
                     "libfranka's control thread can run at SCHED_FIFO 99" if problem is None else problem,
                     "`@realtime - rtprio 99` in /etc/security/limits.d/franka.conf with this user in group "
                     "realtime, or LimitRTPRIO=99 in the unit"))
    soft, hard = memlock or resource.getrlimit(resource.RLIMIT_MEMLOCK)
    ok = soft == resource.RLIM_INFINITY or soft >= LIBFRANKA_MEMLOCK_BYTES
    shown = "unlimited" if soft == resource.RLIM_INFINITY else f"{soft >> 10} KiB"
    out.append(Check("Franka memlock", "pass" if ok else "warn", f"RLIMIT_MEMLOCK {shown}",
                     None if ok else "`@realtime - memlock 102400` in /etc/security/limits.d/franka.conf, or "
                     "LimitMEMLOCK=infinity in the unit"))
    return out


def check_franka_robot(host: str, timeout_s: float = CONNECT_TIMEOUT_S) -> list[Check]:
    """A Franka robot at `host`: its FCI answers libfranka's Connect with the robot server version
    this franky speaks."""
    from tecdard.robots.franka_link import LIBFRANKA_ROBOT_SERVER_VERSION, ROBOT_PORT, server_version
    try:
        status, version = server_version(host, timeout_s)
    except ConnectionRefusedError:
        return [Check(f"Franka robot {host}", "fail", f"port {ROBOT_PORT} refused the connection",
                      "enable FCI in Desk (and open the brakes), and check robot.franka.host")]
    except (OSError, ValueError) as exc:
        return [Check(f"Franka robot {host}", "fail", f"no Connect reply on port {ROBOT_PORT}: "
                      f"{getattr(exc, 'strerror', None) or exc or type(exc).__name__}",
                      "check robot.franka.host, the network to the robot, and that FCI is enabled")]
    if status != 0 or version != LIBFRANKA_ROBOT_SERVER_VERSION:
        return [Check(f"Franka robot {host}", "fail", f"robot server version {version}; this franky (libfranka "
                      f"0.21.2) speaks {LIBFRANKA_ROBOT_SERVER_VERSION}",
                      "install the franky-control release built for the robot's system version, or update the "
                      "robot")]
    return [Check(f"Franka robot {host}", "pass", f"robot server version {version}, as this franky speaks")]


def load_daemon(config_path: str):
    """The config checked as `tecdard run` checks it: (Daemon, None) or (None, Check that failed)."""
    from tecdard.config import Config, ConfigError
    try:
        cfg = Config.load(config_path)
        from tecdard.runtime.daemon import Daemon
        return Daemon(cfg), None
    except ConfigError as exc:
        return None, Check("config", "fail", f"{config_path}: {exc}", "correct the key named (docs: configs/sim.yaml)")


def run_checks(config_path: str) -> list[Check]:
    daemon, failed = load_daemon(config_path)
    checks = [failed or Check("config", "pass", f"{config_path} is valid (the checks of `tecdard run`)")]
    checks += [check_rt_kernel(), check_rtprio(daemon.control_params.rt_priority if daemon else None),
               check_governor()]
    serial_params = getattr(getattr(daemon, "imu", None), "p", None) if daemon and daemon.imu_source == "serial" \
        else None
    checks.append(check_board(serial_params) if daemon else
                  Check("fingertip board", "skip", "the config is invalid"))
    checks.append(check_udev_rule())
    if daemon is not None:
        checks += check_endpoints(daemon.listen, daemon.connect, daemon.robot_name, daemon.tls)
        settings = getattr(daemon.backend, "settings", None)
        backend = type(daemon.backend).__module__
        if backend == "tecdard.robots.ur":
            checks += check_ur_controller(settings.host, daemon.model.name)
        elif backend == "tecdard.robots.franka":
            checks += check_franka_realtime(settings.realtime)
            checks += check_franka_robot(settings.host)
    checks.append(check_kernel_cache())
    return checks


def main(config_path: str, out=None) -> int:
    import sys
    out = out or sys.stdout
    checks = run_checks(config_path)
    for c in checks:
        for line in c.lines():
            print(line, file=out)
    failed = [c for c in checks if c.status == "fail"]
    warned = [c for c in checks if c.status == "warn"]
    print(f"{len(checks)} checks: {len(failed)} failed, {len(warned)} warnings", file=out)
    return 1 if failed else 0
