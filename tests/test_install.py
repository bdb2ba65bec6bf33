"""The project installs under one import root: beside python-control (`pip install control`, whose
import name is `control`), editable and as a built wheel, both import and `tecdard --help` runs.

Each case is a fresh venv. Its dependencies come from this suite's own venv through a .pth line
(pip counts them as installed), so the only downloads are python-control itself and the build
backend, both cached by pip after the first run.
"""
import os
import pathlib
import shutil
import site
import subprocess
import sys
import zipfile

import pytest

from tests.conftest import ROOT

# the slow tier (`make check` leaves it out): fresh venvs, a wheel built
pytestmark = pytest.mark.slow

INSTALL_TIMEOUT_S = 600.0
KERNELS = "tecdard/control/estimators/kernels"
KERNELS_PROBE = """
import sys
from tecdard.control.estimators.kernels import api
print(api.KIND, "numba" in sys.modules, api.__file__)
"""
# Imported in each venv: one module of every folder we install, none that compiles the kernels.
OURS = ("tecdard.cli.main", "tecdard.api.commands", "tecdard.runtime.messages", "tecdard.recording.format",
        "tecdard.tools.localize", "tecdard.verbs", "tecdard.drivers.serial_imu", "tecdard.control.geometry",
        "tecdard.robots.model", "tecdard.sim.world")
PROBE = """
import pathlib, sys, control
import {ours}
assert hasattr(control, "TransferFunction"), control.__file__       # python-control, whole
venv = pathlib.Path(sys.prefix)
assert pathlib.Path(control.__file__).is_relative_to(venv), control.__file__
for name in {names!r}:
    print(name, sys.modules[name].__file__)
"""


def installed_sources() -> dict[str, pathlib.Path]:
    """Every module of the checkout's installed folders, by its path in the wheel."""
    out = {}
    for folder, under in (("tecdard", "tecdard"), ("drivers", "tecdard/drivers"), ("control", "tecdard/control"),
                          ("robots", "tecdard/robots"), ("sim", "tecdard/sim")):
        for path in (ROOT / folder).rglob("*.py"):
            out[f"{under}/{path.relative_to(ROOT / folder).as_posix()}"] = path
    return out


def checkout_copy(dest: pathlib.Path) -> pathlib.Path:
    """The checkout's files (tracked and new, not ignored) copied to dest."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True,
                            check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


def fresh_venv(path: pathlib.Path) -> pathlib.Path:
    """A venv without pip whose site-packages also sees this suite's (the dependencies)."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True, timeout=120)
    py = path / "bin" / "python"
    (ours,) = [p for p in site.getsitepackages() if p.endswith("site-packages")]
    target = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                            capture_output=True, text=True, check=True).stdout.strip()
    # the suite's path, then its own .pth lines (cmeel's adds Pinocchio's prefix), not its editable install
    lines = [ours] + [line for pth in sorted(pathlib.Path(ours).glob("*.pth")) if not pth.name.startswith("__editable__")
                      for line in pth.read_text().splitlines()]
    pathlib.Path(target, "suite-deps.pth").write_text("\n".join(lines) + "\n")
    return py


def pip(py: pathlib.Path, *args: str) -> None:
    res = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--quiet",
                          "--disable-pip-version-check", *args], capture_output=True, text=True,
                         timeout=INSTALL_TIMEOUT_S)
    assert res.returncode == 0, res.stderr[-2000:]


def check(py: pathlib.Path, cwd: pathlib.Path) -> dict:
    """Both import, from outside the checkout; returns where each of ours came from."""
    code = PROBE.format(ours=", ".join(OURS), names=OURS)
    res = subprocess.run([str(py), "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    help_ = subprocess.run([str(py.parent / "tecdard"), "--help"], cwd=cwd, capture_output=True, text=True,
                           timeout=120)
    assert help_.returncode == 0 and "localize" in help_.stdout and "run" in help_.stdout, help_.stderr
    return dict(line.split(" ", 1) for line in res.stdout.splitlines())


@pytest.mark.parametrize("how", ["editable", "wheel"])
def test_tecdar_installs_beside_python_control(tmp_path, how):
    py = fresh_venv(tmp_path / "venv")
    pip(py, "control")
    if how == "editable":
        pip(py, "--no-deps", "-e", str(ROOT))
    else:
        dist, src = tmp_path / "dist", checkout_copy(tmp_path / "src")     # setuptools builds in its source tree
        res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(dist),
                              str(src)], capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
        assert res.returncode == 0, res.stderr[-2000:]
        (wheel,) = dist.glob("tecdar-*.whl")
        with zipfile.ZipFile(wheel) as zf:
            names = set(zf.namelist())
        roots = {name.split("/")[0] for name in names}
        assert roots == {"tecdard", wheel.name.split("-")[0] + "-" + wheel.name.split("-")[1] + ".dist-info"}, roots
        missing = sorted(set(installed_sources()) - names)
        assert not missing, f"modules the wheel leaves out (pyproject's packages): {missing}"
        # the ament interface package's definitions, which the node encodes with (their folders are packages)
        interfaces = {f"tecdard/ros2/tecdar_msgs/{p.relative_to(ROOT / 'ros2' / 'tecdar_msgs').as_posix()}"
                      for p in (ROOT / "ros2" / "tecdar_msgs").rglob("*") if p.is_file()}
        assert interfaces and not interfaces - names, sorted(interfaces - names)
        # setup.py compiled the estimator's kernels into it: a platform wheel
        assert any(n.startswith(f"{KERNELS}/_compiled.") and n.endswith(".so") for n in names), sorted(names)
        assert f"{KERNELS}/_compiled.digest" in names and "-cp311-" in wheel.name, wheel.name
        pip(py, "--no-deps", str(wheel))
    files = check(py, tmp_path)
    if how == "wheel":
        # the first start after installing the wheel loads the kernels and compiles nothing (no numba)
        res = subprocess.run([str(py), "-c", KERNELS_PROBE], cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr[-2000:]
        kind, numba_imported, where = res.stdout.split()
        assert (kind, numba_imported) == ("aot", "False") and pathlib.Path(where).is_relative_to(tmp_path / "venv")
    if how == "wheel":
        the_shipped_data_is_found_in_the_installed_wheel(py, tmp_path)
    for name, path in files.items():
        where = pathlib.Path(path)
        if how == "editable":
            assert where.is_relative_to(ROOT), (name, path)          # the checkout's own folders
        else:
            assert where.is_relative_to(tmp_path / "venv"), (name, path)


SHIPPED_PROBE = """
from tecdard import shipped
print(shipped.config("sim.yaml")); print(shipped.systemd("99-tecdar-imu.rules")); print(shipped.host_board())
"""
DEMO_TIMEOUT_S = 300.0


def the_shipped_data_is_found_in_the_installed_wheel(py: pathlib.Path, tmp_path: pathlib.Path) -> None:
    """Issue 47: the configs, the udev rule and the host board come from the installed package (no path
    walked up from a source file): `tecdard doctor --config` on the installed sim config (on a free port:
    a user's daemon may hold 7507) passes, and `tecdard demo` on it rotates the cutter, from outside the
    checkout."""
    import yaml

    from tecdard.tools.demo import free_port
    venv = tmp_path / "venv"
    res = subprocess.run([str(py), "-c", SHIPPED_PROBE], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    config, rule, board = (pathlib.Path(line) for line in res.stdout.split())
    for path in (config, rule, board):
        assert path.is_file() and path.is_relative_to(venv), path
    assert os.access(board, os.X_OK), board
    cfg = yaml.safe_load(config.read_text())
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    mine = tmp_path / "sim.yaml"
    mine.write_text(yaml.safe_dump(cfg))
    doctor = subprocess.run([str(venv / "bin" / "tecdard"), "doctor", "--config", str(mine)], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr
    assert "PASS  config:" in doctor.stdout and str(rule) in doctor.stdout, doctor.stdout
    demo = subprocess.run([str(venv / "bin" / "tecdard"), "demo", "--config", str(config)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=DEMO_TIMEOUT_S)
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-2000:]
    assert "hinge error" in demo.stdout and "angle reached" in demo.stdout, demo.stdout
