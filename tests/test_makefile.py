"""Issue 50 item 8: a .venv made by another Python than PY_BOOT's is made again (README's fix for Ubuntu 22.04,
`make run PY_BOOT=python3.11` after a failed start on 3.10, reused the 3.10 venv and failed the same way), and a
Python older than 3.11 is refused in one line that says what to run."""
import subprocess
import sys

import pytest

from tests.conftest import ROOT


def fake_python(path, version: str):
    """An executable that answers the Makefile's version question with `version`, and its 3.11 check as that
    version would."""
    major, minor = (int(x) for x in version.split("."))
    path.write_text(f"#!/bin/sh\ncase \"$2\" in *exit*) exit {int((major, minor) < (3, 11))};; esac\necho {version}\n")
    path.chmod(0o755)
    return path


def make(*args):
    return subprocess.run(["make", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=60)


def test_a_venv_of_another_python_is_made_again_and_one_of_the_same_is_kept(tmp_path):
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    fake_python(venv / "bin" / "python", "3.10")
    res = make("-n", "lint", f"VENV={venv}", f"PY_BOOT={sys.executable}")
    this = "%d.%d" % sys.version_info[:2]
    assert f"make: {venv} is Python 3.10's, {sys.executable} is {this}: {venv} is made again" in res.stdout
    assert not venv.exists()
    (venv / "bin").mkdir(parents=True)
    fake_python(venv / "bin" / "python", this)
    res = make("-n", "lint", f"VENV={venv}", f"PY_BOOT={sys.executable}")
    assert "made again" not in res.stdout and venv.exists()


def test_a_python_older_than_3_11_is_refused_in_one_line(tmp_path):
    old = fake_python(tmp_path / "python3.10", "3.10")
    res = make(str(tmp_path / "venv" / "bin" / "python"), f"VENV={tmp_path / 'venv'}", f"PY_BOOT={old}")
    assert res.returncode != 0 and not (tmp_path / "venv").exists()
    assert f"make: {old} is Python 3.10; tecdar needs 3.11 or later: make " in res.stdout
    assert "PY_BOOT=python3.11" in res.stdout


@pytest.mark.slow
@pytest.mark.alone          # it reinstalls the package into the venv the other worker's tests run from
def test_the_install_prints_no_warning_of_setuptools():
    """Issue 50 item 15: `make install` printed setuptools' warnings, one for each folder of ros2/tecdar_msgs
    (importable, yet not in pyproject's packages), and its notice that the install is editable. The
    Makefile's own pip command, run as it runs it (the package alone, into this venv), prints nothing."""
    import os
    import re
    res = make("-n", "install", "VENV=.venv")
    (line,) = [x for x in res.stdout.splitlines() if re.search(r"pip install --quiet -e", x)]
    env_part, _, cmd = line.partition(" .venv/bin/python ")
    assert env_part.startswith("PYTHONWARNINGS="), line
    name, _, value = env_part.partition("=")
    out = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "-e", "."], cwd=ROOT,
                         env={**os.environ, name: value.strip('"')}, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "Warning" not in out.stderr and "warning" not in out.stdout.lower(), out.stderr[:3000]
