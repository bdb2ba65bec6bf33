"""`tecdard doctor` (issue 17): a line per check, the fix under each non-pass, exit 1 on a failure."""
import io
import os
import socket
import types

import pytest

from tecdard.config import dump_yaml
from tecdard.host import check_rt_kernel
from tecdard.robots.franka import check_franka_realtime, check_franka_robot
from tecdard.robots.ur import check_ur_controller
from tecdard.tools import doctor
from tecdard.tools.demo import free_port
from tests.conftest import ROOT, sim_config


def test_the_shipped_config_on_this_host(tmp_path):
    cfg = sim_config(**{"zenoh.listen": [f"tcp/127.0.0.1:{free_port()}"]})
    path = tmp_path / "tecdard.yaml"
    path.write_text(dump_yaml(cfg))
    out = io.StringIO()
    code = doctor.main(str(path), out)
    lines = out.getvalue().splitlines()
    names = {"config", "real-time kernel", "SCHED_FIFO", "CPU governor", "fingertip board", "udev rule",
             "compiled-code cache"}
    checks = [ln for ln in lines if ln[:4] in ("PASS", "WARN", "FAIL", "SKIP")]
    assert names <= {ln[6:].split(":")[0] for ln in checks}
    assert any(ln.startswith("PASS  zenoh.listen") for ln in checks)
    assert lines[0].startswith("PASS  config") and code == 0, out.getvalue()
    for i, ln in enumerate(lines[:-1]):          # every warning says what to do
        if ln.startswith(("WARN", "FAIL")):
            assert lines[i + 1].startswith("      fix: "), ln


def test_a_bad_config_fails_with_the_runs_own_line(tmp_path):
    path = tmp_path / "tecdard.yaml"
    path.write_text(dump_yaml(sim_config(**{"control.tick_ms": 20})))
    out = io.StringIO()
    assert doctor.main(str(path), out) == 1
    first = out.getvalue().splitlines()[0]
    assert first.startswith("FAIL  config") and "control.tick_ms: unknown option" in first


def test_rt_kernel(tmp_path):
    flag = tmp_path / "realtime"
    flag.write_text("1\n")
    assert check_rt_kernel(str(flag), "#1 SMP").status == "pass"
    assert check_rt_kernel(str(tmp_path / "none"), "#1 SMP PREEMPT_RT Debian").status == "pass"
    c = check_rt_kernel(str(tmp_path / "none"), "#1 SMP PREEMPT_DYNAMIC")
    assert c.status == "warn" and "linux-image-rt" in c.fix


def test_governor(tmp_path):
    for i, g in enumerate(["performance", "performance"]):
        (tmp_path / f"cpu{i}").mkdir()
        (tmp_path / f"cpu{i}" / "scaling_governor").write_text(g + "\n")
    pattern = str(tmp_path / "cpu[0-9]*" / "scaling_governor")
    assert doctor.check_governor(pattern).status == "pass"
    (tmp_path / "cpu1" / "scaling_governor").write_text("powersave\n")
    c = doctor.check_governor(pattern)
    assert c.status == "warn" and "powersave on 1 of 2" in c.detail and "cpupower" in c.fix
    assert doctor.check_governor(str(tmp_path / "nothing*")).status == "warn"


def test_busy_cores_and_isolated_cores(tmp_path):
    """Issue 37: a core busy at rest, or none isolated, is a warning naming the cores and the fix."""
    c = doctor.check_busy_cores({"cpu0": 12.0, "cpu1": 97.0})
    assert c.status == "warn" and "1 of 2 cores over 50 % busy (cpu0 12 %, cpu1 97 %)" in c.detail
    assert "isolcpus" in c.fix
    assert doctor.check_busy_cores({"cpu0": 12.0, "cpu1": 20.0}).status == "pass"
    stat = tmp_path / "stat"
    stat.write_text("cpu  10 0 10 100 0 0 0 0 0 0\ncpu0 5 0 5 50 0 0 0 0 0 0\ncpu1 5 0 5 50 0 0 0 0 0 0\n")
    busy = doctor.cpu_busy_pct(str(stat), 0.0)
    assert busy == {"cpu0": 0.0, "cpu1": 0.0}                # nothing changed between the two reads
    real = doctor.cpu_busy_pct(sample_s=0.05)                 # this host's own
    assert real and all(name.startswith("cpu") and 0.0 <= pct <= 100.0 for name, pct in real.items())
    iso, cmdline = tmp_path / "isolated", tmp_path / "cmdline"
    iso.write_text("\n")
    cmdline.write_text("BOOT_IMAGE=/vmlinuz root=/dev/sda1 quiet\n")
    c = doctor.check_isolated_cores(str(iso), str(cmdline))
    assert c.status == "warn" and "no core is isolated" in c.detail and "CPUAffinity=1" in c.fix
    iso.write_text("1\n")
    cmdline.write_text("quiet isolcpus=1 nohz_full=1\n")
    c = doctor.check_isolated_cores(str(iso), str(cmdline))
    assert c.status == "pass" and "isolated CPUs 1; nohz_full 1" in c.detail


def test_rtprio_is_tried_on_a_thread_of_its_own():
    before = os.sched_getscheduler(0)
    c = doctor.check_rtprio(10)
    assert c.status in ("pass", "warn") and "control.rt_priority" in c.detail
    assert os.sched_getscheduler(0) == before          # the caller's own policy is untouched


def test_apply_rt_priority_says_so_in_one_line_when_refused(monkeypatch, caplog):
    import logging
    from tecdard import host
    from tecdard.runtime import realtime

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(host.os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.INFO, logger="tecdar"):
        assert realtime.apply_rt_priority(80) is False
    (line,) = [r.getMessage() for r in caplog.records]
    assert "control.rt_priority 80" in line and "refused" in line and "SCHED_OTHER" in line
    assert realtime.apply_rt_priority(None) is False


def test_board_by_port_and_by_vid_pid(tmp_path):
    from tecdard.drivers.serial_imu import SerialParams, check_board
    c = check_board(SerialParams(port="/dev/tecdar-imu-not-here"))
    assert c.status == "fail" and "does not exist" in c.detail and "plug" in c.fix
    c = check_board(SerialParams(port=str(tmp_path / "tecdar-imu")))     # the udev rule's link, absent
    assert c.status == "fail" and "/dev/tecdar-imu" in c.fix
    master, slave = os.openpty()
    try:
        pty = os.ttyname(slave)
        assert check_board(SerialParams(port=pty)).status == "pass"
        info = types.SimpleNamespace(device=pty, vid=0x0483, pid=0x5740, serial_number="A1")
        other = types.SimpleNamespace(device="/dev/ttyUSB9", vid=0x1a86, pid=0x7523, serial_number=None)
        assert check_board(SerialParams(vid=0x0483, pid=0x5740), lambda: [other, info]).status == "pass"
        c = check_board(SerialParams(vid=0x0483, pid=0x5740, serial_number="B2"), lambda: [other, info])
        assert c.status == "fail" and "0483:5740 serial B2" in c.detail and "1a86:7523" in c.detail
    finally:
        os.close(master)
        os.close(slave)


def test_udev_rule(tmp_path):
    assert doctor.check_udev_rule([str(tmp_path)]).status == "warn"
    (tmp_path / doctor.UDEV_RULE.name).write_text(doctor.UDEV_RULE.read_text())
    assert doctor.check_udev_rule([str(tmp_path)]).status == "pass"
    (tmp_path / doctor.UDEV_RULE.name).write_text("# someone's edit\n")
    assert doctor.check_udev_rule([str(tmp_path)]).status == "warn"
    rule = (ROOT / "systemd" / "99-tecdar-imu.rules").read_text()
    assert 'SYMLINK+="tecdar-imu"' in rule and 'GROUP="dialout"' in rule and "0403" in rule


@pytest.mark.slow
def test_endpoints_free_taken_reachable_unreachable():
    free = f"tcp/127.0.0.1:{free_port()}"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        checks = doctor.check_endpoints([free, busy], [busy, free])
    assert [c.status for c in checks] == ["pass", "fail", "pass", "fail"], checks
    assert "cannot listen" in checks[1].detail and "zenoh.mode" in checks[1].fix
    assert "unreachable" in checks[3].detail


@pytest.mark.slow
def test_an_endpoint_held_by_a_running_daemon_passes(shared_daemon):
    (c,) = doctor.check_endpoints([shared_daemon.endpoint], [])
    assert c.status == "pass" and "running tecdard" in c.detail


# -- a UR rig ---------------------------------------------------------------------------------

def ur5e_config(tmp_path, host: str) -> str:
    """configs/ur5e.yaml as shipped, pointed at `host`, listening on a free port."""
    import yaml
    cfg = yaml.safe_load((ROOT / "configs" / "ur5e.yaml").read_text())
    cfg["robot"]["ur"]["host"] = host
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    path = tmp_path / "ur5e.yaml"
    path.write_text(dump_yaml(cfg))
    return str(path)


@pytest.mark.slow
def test_the_shipped_ur5e_config_is_valid_and_its_controller_is_checked(tmp_path):
    pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    from tests.fakes.fake_ur import FakeController, free_loopback_host
    fake = FakeController(free_loopback_host(), arm="UR5e")
    try:
        out = io.StringIO()
        doctor.main(ur5e_config(tmp_path, fake.host), out)
    finally:
        fake.close()
    text = out.getvalue()
    assert text.splitlines()[0].startswith("PASS  config"), text
    assert f"PASS  UR controller {fake.host}: dashboard, script and RTDE ports answer" in text
    assert "PASS  UR arm: UR5e, software 5.11" in text
    # the board is the rig's (imu.source serial): checked at its configured port, which is not here
    assert "FAIL  fingertip board: /dev/tecdar-imu does not exist" in text, text


@pytest.mark.parametrize("arm,remote,expect", [
    ("UR5", True, "FAIL  UR arm: UR5, software 3.15.7.0"),             # a CB3 UR5 where a UR5e is configured
    ("UR5e", False, "FAIL  UR remote control: the controller is in local control"),
])
def test_a_ur_controller_that_cannot_serve_this_config_fails(tmp_path, arm, remote, expect):
    pytest.importorskip("rtde_control", reason="ur-rtde is installed by `make test` (extra `ur`)")
    from tests.fakes.fake_ur import FakeController, free_loopback_host
    fake = FakeController(free_loopback_host(), arm=arm, remote_control=remote)
    try:
        checks = check_ur_controller(fake.host, "ur5e")
    finally:
        fake.close()
    lines = [ln for c in checks for ln in c.lines()]
    assert any(ln.startswith(expect) for ln in lines), lines
    assert any(ln.startswith("      fix: ") for ln in lines)


def test_no_ur_controller_at_the_host_fails_naming_the_ports():
    from tests.fakes.fake_ur import free_loopback_host
    (check,) = check_ur_controller(free_loopback_host(), "ur5e")
    assert check.status == "fail" and "dashboard 29999" in check.detail and "RTDE 30004" in check.detail


def fr3_config(tmp_path, host: str, realtime: str = "enforce") -> str:
    import yaml
    cfg = yaml.safe_load((ROOT / "configs" / "fr3.yaml").read_text())
    cfg["robot"]["franka"]["host"] = host
    cfg["robot"]["franka"]["realtime"] = realtime
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    cfg["imu"]["serial"]["port"] = str(tmp_path / "no-board")
    path = tmp_path / "fr3.yaml"
    path.write_text(dump_yaml(cfg))
    return str(path)


@pytest.mark.slow
def test_the_shipped_fr3_config_is_valid_and_its_robot_and_realtime_are_checked(tmp_path):
    """Issue 22: doctor tells a Franka user whether the host is fit for realtime enforcement, and
    whether the robot's server speaks this franky's version (franky-sim here)."""
    pytest.importorskip("franky_sim", reason="franky-sim is installed by `make test` (extra `franka-sim`)")
    from tests.fakes.franka_sim import ServerProcess
    srv = ServerProcess()
    try:
        out = io.StringIO()
        doctor.main(fr3_config(tmp_path, srv.host), out)
    finally:
        srv.close()
    text = out.getvalue()
    assert text.splitlines()[0].startswith("PASS  config"), text
    assert f"PASS  Franka robot {srv.host}: robot server version 10, as this franky speaks" in text
    # this CI host has no PREEMPT_RT kernel: enforcement would fail, and doctor says so with the fix
    kernel = [ln for ln in text.splitlines() if "Franka realtime kernel" in ln]
    assert kernel and kernel[0][:4] in ("PASS", "FAIL"), text
    if kernel[0].startswith("FAIL"):
        assert "RealtimeException" in kernel[0]
    assert "Franka SCHED_FIFO 99" in text and "Franka memlock" in text
    assert f"FAIL  fingertip board: {tmp_path / 'no-board'} does not exist" in text, text


def test_franka_realtime_checks_read_the_host():
    rt = check_franka_realtime("enforce", "/nonexistent", "#1 SMP PREEMPT_RT", memlock=(-1, -1))
    kernel, _, memlock = rt
    assert kernel.status == "pass" and memlock.status == "pass"
    low = check_franka_realtime("enforce", "/nonexistent", "#1 SMP PREEMPT_DYNAMIC", memlock=(65536, 65536))
    assert low[0].status == "fail" and "RealtimeException" in low[0].detail and low[0].fix
    assert low[2].status == "warn" and "64 KiB" in low[2].detail and "memlock 102400" in low[2].fix
    (ignored,) = check_franka_realtime("ignore")
    assert ignored.status == "warn" and "franky-sim" in ignored.detail


@pytest.mark.slow
def test_a_franka_robot_of_another_version_or_none_fails(tmp_path):
    pytest.importorskip("franky_sim", reason="franky-sim is installed by `make test` (extra `franka-sim`)")
    from tests.fakes.franka_sim import ServerProcess, free_franka_host
    srv = ServerProcess("--reply-version", "9")
    try:
        (check,) = check_franka_robot(srv.host)
    finally:
        srv.close()
    assert check.status == "fail" and "robot server version 9" in check.detail and "speaks 10" in check.detail
    (none,) = check_franka_robot(free_franka_host())
    assert none.status == "fail" and "refused" in none.detail and "FCI" in none.fix


# -- issue 33: the rig configs, a listener that is no UR, a missing config ---------------------------

@pytest.mark.parametrize("name", ["sim.yaml", "ur5e.yaml", "fr3.yaml"])
def test_run_checks_on_each_shipped_config_checks_its_board(tmp_path, name):
    """`doctor` read an attribute that had been renamed and skipped the board on exactly the rig
    configs: run_checks itself, on each shipped config, checks the board the config names."""
    import yaml
    from tests.fakes.fake_ur import free_loopback_host
    cfg = yaml.safe_load((ROOT / "configs" / name).read_text())
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    if "ur" in cfg["robot"]:
        cfg["robot"]["ur"]["host"] = free_loopback_host()           # nothing there
    if "franka" in cfg["robot"]:
        cfg["robot"]["franka"]["host"] = free_loopback_host((1337,))
    if cfg.get("imu", {}).get("source") == "serial":
        cfg["imu"]["serial"]["port"] = str(tmp_path / "no-board")
    path = tmp_path / name
    path.write_text(dump_yaml(cfg))
    checks = {c.name: c for c in doctor.run_checks(str(path))}
    assert checks["config"].status == "pass", checks["config"]
    board = checks["fingertip board"]
    if name == "sim.yaml":
        assert board.status in ("pass", "skip") and "serial" not in board.detail.split(":")[0]
    else:
        assert board.status == "fail" and f"{tmp_path / 'no-board'} does not exist" in board.detail, board
    rig = [c for c in checks.values() if c.name.startswith(("UR controller", "Franka robot"))]
    assert (name == "sim.yaml") == (not rig)
    assert all(c.status == "fail" for c in rig), rig                       # no controller at that host


@pytest.mark.slow
def test_a_listener_that_is_not_a_ur_dashboard_fails(tmp_path):
    """The UR check passed on any TCP listener: it now reads the dashboard's greeting."""
    from tecdard.robots.ur import check_ur_controller
    from tests.fakes.fake_ur import free_loopback_host
    host = free_loopback_host()
    servers = [socket.create_server((host, port)) for port in (29999, 30003, 30004)]
    try:
        (check,) = check_ur_controller(host, "ur5e")
    finally:
        for s in servers:
            s.close()
    assert check.status == "fail" and "29999 said nothing, not a UR dashboard's greeting" in check.detail, check
    assert "robot.ur.host" in check.fix


def test_a_missing_config_names_its_path_once_and_how_to_make_one(tmp_path):
    path = tmp_path / "etc" / "tecdard.yaml"
    out = io.StringIO()
    assert doctor.main(str(path), out) == 1
    first, fix = out.getvalue().splitlines()[:2]
    assert first == f"FAIL  config: {path}: no such file"
    assert "configs/ur5e.yaml" in fix and str(path) in fix and "key named" not in fix
