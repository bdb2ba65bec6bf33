"""`tecdard doctor`: is this host ready to run the daemon beside a real arm?

One line per check, PASS, WARN, FAIL or SKIP, with the fix under anything that is not a pass;
the exit status is 1 when any check fails. A warning is something the daemon runs with but an
operator should know (a kernel that is not real-time, a CPU governor that scales down); a failure
is something `tecdard run` would refuse or that leaves the daemon without its data (the config, the
board, the endpoint).

The host's checks are here; the daemon's robot backend and its IMU source give their own for their
devices (RobotBackend.checks: a UR controller's ports and arm, a Franka's realtime fitness and robot
server; ImuSource.checks: the fingertip board at its port). Every check reads the host through
arguments with the real defaults, so the tests can point them at a scratch directory.
"""
from __future__ import annotations

import glob
import pathlib
import socket

from tecdard import shipped
from tecdard.host import Check, can_set_fifo, check_rt_kernel, rtprio_limit

UDEV_RULE = shipped.systemd("99-tecdar-imu.rules")
UDEV_RULE_DIRS = ("/etc/udev/rules.d", "/run/udev/rules.d", "/usr/lib/udev/rules.d", "/lib/udev/rules.d")
DEFAULT_RT_PRIORITY = 80      # what the doctor tries when the config names none
CONNECT_TIMEOUT_S = 1.0


# -- the host ------------------------------------------------------------------
def check_rtprio(priority: int | None) -> Check:
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


BUSY_CORE_PCT = 50.0          # a core busier than this at rest leaves the tick waiting behind its work
LOAD_SAMPLE_S = 0.5           # s, how long the doctor watches the cores


def cpu_busy_pct(stat_path: str = "/proc/stat", sample_s: float = LOAD_SAMPLE_S) -> dict[str, float]:
    """Each CPU's busy share over `sample_s` (everything but idle and iowait), in %."""
    import time

    def read():
        out = {}
        for line in pathlib.Path(stat_path).read_text().splitlines():
            name, *fields = line.split()
            if name.startswith("cpu") and name != "cpu" and len(fields) >= 5:
                ticks = [int(x) for x in fields[:8]]
                out[name] = (sum(ticks), ticks[3] + ticks[4])
        return out
    before = read()
    time.sleep(sample_s)
    after = read()
    busy = {}
    for name, (total, idle) in after.items():
        t0, i0 = before.get(name, (total, idle))
        busy[name] = 100.0 * (1.0 - (idle - i0) / (total - t0)) if total > t0 else 0.0
    return busy


def check_busy_cores(busy: dict[str, float] | None = None) -> Check:
    """A core already busy (another process at rest, the daemon's own included when it runs) makes the
    control tick wait for the OS as well as for the GIL: its lateness goes over the 1 ms budget."""
    try:
        busy = cpu_busy_pct() if busy is None else busy
    except (OSError, ValueError) as exc:
        return Check("busy cores", "warn", f"cannot read /proc/stat: {exc}")
    loaded = {name: pct for name, pct in busy.items() if pct > BUSY_CORE_PCT}
    shown = ", ".join(f"{name} {pct:.0f} %" for name, pct in sorted(busy.items()))
    if not loaded:
        return Check("busy cores", "pass", f"no core over {BUSY_CORE_PCT:.0f} % busy ({shown})")
    return Check("busy cores", "warn", f"{len(loaded)} of {len(busy)} cores over {BUSY_CORE_PCT:.0f} % busy ({shown}): "
                 "the control tick waits behind that work, and its lateness can exceed its budget",
                 "find the process (`top -1`) and move it, or give the daemon a core of its own (isolcpus=, and "
                 "CPUAffinity= in the unit)")


def check_isolated_cores(isolated_path: str = "/sys/devices/system/cpu/isolated",
                         cmdline_path: str = "/proc/cmdline") -> Check:
    """isolcpus= (or nohz_full=) keeps the scheduler's other work off the cores the daemon is pinned to."""
    try:
        isolated = pathlib.Path(isolated_path).read_text().strip()
    except OSError:
        isolated = ""
    try:
        args = pathlib.Path(cmdline_path).read_text().split()
        nohz = [a.split("=", 1)[1] for a in args if a.startswith("nohz_full=")]
    except OSError:
        nohz = []
    if isolated or nohz:
        return Check("isolated cores", "pass", f"isolated CPUs {isolated or '-'}; nohz_full {','.join(nohz) or '-'}: "
                     "pin the daemon there (CPUAffinity= in the unit)")
    return Check("isolated cores", "warn", "no core is isolated (isolcpus=, nohz_full=): the control tick shares its "
                 "cores with every other process",
                 "on a dedicated rig PC: isolcpus=1 nohz_full=1 on the kernel command line and CPUAffinity=1 in the "
                 "unit; with SCHED_FIFO this bounds the tick's lateness")


# -- the fingertip board ---------------------------------------------------------
def check_udev_rule(dirs=UDEV_RULE_DIRS, rule: pathlib.Path = UDEV_RULE) -> Check:
    fix = (f"sudo install -m 644 {rule} /etc/udev/rules.d/ && sudo udevadm control --reload && "
           "sudo udevadm trigger --subsystem-match=tty --subsystem-match=usb-serial")
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
    """A daemon answers at the endpoint: with TLS, one holding a certificate of the same name as this one's."""
    try:
        from tecdard.api.session import DAEMON_NAME, cert_common_name
        from tecdard.api.client import Client
        name = (cert_common_name(tls.cert) or DAEMON_NAME) if tls is not None else DAEMON_NAME
        with Client(endpoint, robot=robot, tls=tls, open_timeout_s=CONNECT_TIMEOUT_S, daemon_name=name) as cli:
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


def load_daemon(config_path: str):
    """The config checked as `tecdard run` checks it: (Daemon, None) or (None, Check that failed)."""
    from tecdard.config import Config, ConfigError
    if not pathlib.Path(config_path).is_file():
        return None, Check("config", "fail", f"{config_path}: no such file",
                           f"start from a shipped one: `sudo install -D -m 644 {shipped.config('ur5e.yaml')} "
                           f"{config_path}` (or fr3.yaml, sim.yaml), edit it, or name yours with --config")
    try:
        cfg = Config.load(config_path)
        from tecdard.runtime.daemon import Daemon
        return Daemon(cfg), None
    except ConfigError as exc:
        text = str(exc)
        return None, Check("config", "fail", text if text.startswith(str(config_path)) else f"{config_path}: {text}",
                           "correct the option named (`tecdard options` lists every one, with its limits)")


def run_checks(config_path: str) -> list[Check]:
    """The host's checks, then the daemon's own (its endpoints, the compiled-code cache) and those its
    robot backend and its IMU source give for their devices (RobotBackend.checks, ImuSource.checks)."""
    daemon, failed = load_daemon(config_path)
    checks = [failed or Check("config", "pass", f"{config_path} is valid (the checks of `tecdard run`)")]
    checks += [check_rt_kernel(), check_rtprio(daemon.control_params.rt_priority if daemon else None),
               check_governor(), check_isolated_cores(), check_busy_cores()]
    checks += daemon.imu.checks() if daemon else [Check("fingertip board", "skip", "the config is invalid")]
    checks.append(check_udev_rule())
    if daemon is not None:
        checks += check_endpoints(daemon.zenoh.listen, daemon.zenoh.connect, daemon.robot_name, daemon.zenoh.tls)
        checks += daemon.backend.checks()
        from tecdard.robots.gripper import check_gripper
        checks.append(check_gripper(daemon.gripper_params, daemon.gripper_kind, daemon.robot_section))
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


def add_parser(sub) -> None:
    p = sub.add_parser("doctor", help="check whether this host is ready to run the daemon beside a real arm")
    p.add_argument("--config", default="/etc/tecdar/tecdard.yaml", help="the daemon's config (default: the unit's)")
    p.set_defaults(func=lambda args: main(args.config))
