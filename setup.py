"""setuptools' hooks beside pyproject.toml: a wheel (and `pip install .`) carries the estimator's kernels
compiled ahead of time, so the first start after installing it loads them instead of compiling with
numba's JIT (some 60 s). Everything else about the package is in pyproject.toml.

The kernels are built for the CPU of the machine that builds the wheel (as `tecdard warm` builds them);
TECDAR_KERNELS_CPU=generic builds them for any x86-64 (a wheel for other machines, some 15 % slower on
the long loops). TECDAR_KERNELS_BUILD=0 leaves them out; so does a build that fails (no C compiler),
with one line: the first start then compiles them, or `tecdard warm` builds them later.
An editable install builds nothing here: `make` runs `tecdard warm` beside the checkout's sources.

The wheel also carries the firmware's host board (tecdard/firmware/host-board, the simulator's
sim-firmware source; tecdard.shipped.host_board finds it), built with the host's cc as `make firmware`
builds it; without a C compiler it is left out with one line, and sim.host_board names one.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

KERNELS = os.path.join("tecdard", "control", "estimators", "kernels")
HOST_BOARD = os.path.join("tecdard", "firmware", "host-board")


class BuildPyWithKernels(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("TECDAR_KERNELS_BUILD", "1") == "0":
            return
        out = os.path.join(self.build_lib, KERNELS)
        env = {**os.environ, "PYTHONPATH": os.path.abspath(self.build_lib), "TECDAR_KERNELS": "jit"}
        res = subprocess.run([sys.executable, "-m", "tecdard.control.estimators.kernels.build", out], env=env,
                             capture_output=True, text=True)
        if res.returncode != 0:
            last = (res.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"tecdar: the estimator's kernels were not compiled ahead of time ({last}); the first start "
                  "compiles them (numba's JIT), or `tecdard warm` builds them", file=sys.stderr)
        self._build_host_board()

    def _build_host_board(self) -> None:
        with tempfile.TemporaryDirectory(prefix="tecdar-firmware-") as tmp:
            res = subprocess.run(["make", "-s", "-C", "firmware", f"BUILD={tmp}", f"{tmp}/host-board"],
                                 capture_output=True, text=True)
            if res.returncode != 0:
                last = ((res.stderr or res.stdout).strip().splitlines() or ["no output"])[-1]
                print(f"tecdar: the firmware's host board is not in the wheel ({last}); sim-firmware needs "
                      "sim.host_board then", file=sys.stderr)
                return
            out = os.path.join(self.build_lib, HOST_BOARD)
            os.makedirs(os.path.dirname(out), exist_ok=True)
            shutil.copy2(os.path.join(tmp, "host-board"), out)


class KernelsDistribution(Distribution):
    """The wheel holds a compiled extension: tagged for this Python and platform, not py3-none-any."""

    def has_ext_modules(self):
        return os.environ.get("TECDAR_KERNELS_BUILD", "1") != "0"


setup(cmdclass={"build_py": BuildPyWithKernels}, distclass=KernelsDistribution)
