# tecdar: `make run` (demo on the simulated robot), `make test`, `make check` (quick tier), `make bench`,
# `make firmware` (the fingertip board's firmware: the host board and the STM32F405 image), `make fingertip` (the soft
# fingertip's parts as STL files, checked closed, and its drawing).
PY_BOOT ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# the estimator's kernels compiled ahead of time (control/estimators/kernels/build.py): a start loads
# them without numba; the tests also compile them with numba's JIT (into its cache, on the second core
# while the build runs), since they test the kernels' sources themselves
KERNELS := $(wildcard control/estimators/kernels/*.py)
WARM := $(VENV)/.warm
WARM_JIT := $(VENV)/.warm-jit

.PHONY: install run test check lint bench firmware fingertip clean

# A machine whose environment says PYTHONDONTWRITEBYTECODE (ours does) has every process compile the project's
# sources again: the test runner's assertion rewriting of ~80 modules, each daemon and CLI a test starts. Our
# commands write the bytecode caches (__pycache__, which .gitignore keeps out of the repository).
unexport PYTHONDONTWRITEBYTECODE

# A .venv made by another Python than PY_BOOT's (a start that failed on Python 3.10, then the README's
# `PY_BOOT=python3.11`) is made again, not reused: its packages are that other Python's.
PY_VERSION = import sys; print("%d.%d" % sys.version_info[:2])
VENV_PY := $(shell [ -x $(PY) ] && $(PY) -c '$(PY_VERSION)' 2>/dev/null)
BOOT_PY := $(shell $(PY_BOOT) -c '$(PY_VERSION)' 2>/dev/null)
ifneq ($(VENV_PY),)
ifneq ($(VENV_PY),$(BOOT_PY))
$(info make: $(VENV) is Python $(VENV_PY)'s, $(PY_BOOT) is $(or $(BOOT_PY),missing): $(VENV) is made again)
$(shell rm -rf $(VENV))
endif
endif

$(PY):
	@$(PY_BOOT) -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null || { echo "make: $(PY_BOOT) is Python $(or $(BOOT_PY),missing); tecdar needs 3.11 or later: make $(MAKECMDGOALS) PY_BOOT=python3.11 (README, Python)"; exit 1; }
	$(PY_BOOT) -m venv $(VENV)

# an editable install is what we want (a rig's `git pull` takes effect): setuptools' notice that it is
# one is silenced by its message, and nothing else (its other warnings are mended, tests/test_makefile.py)
PIP := PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip

$(STAMP): $(PY) pyproject.toml
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -e '.[test,ur,viz,bench,franka,franka-sim,ros2,ros2-test,fleet,lerobot,lerobot-test]'
	touch $(STAMP)

$(WARM): $(STAMP) $(KERNELS)
	$(PY) -m tecdard warm
	touch $(WARM)

$(WARM_JIT): $(STAMP) $(KERNELS)
	$(PY) -m tecdard warm --jit
	touch $(WARM) $(WARM_JIT)

# a rig's install: the daemon with the arms' clients and the viewers, none of the test, bench or
# simulator extras (`make run` and `make test` install those into the same .venv when asked)
install: $(PY)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -e '.[ur,franka,viz,ros2,fleet]'
	$(PY) -m tecdard warm

run: $(WARM)
	$(PY) -m tecdard demo --config configs/sim.yaml

# the firmware's tests build it with the host's cc; the board image and its QEMU run need Debian's cross
# toolchain and QEMU, which .ci/run installs (as root)
CROSS_TOOLS = command -v arm-none-eabi-gcc >/dev/null && command -v qemu-system-arm >/dev/null
NO_CROSS = echo "make: no arm-none-eabi-gcc or qemu-system-arm here: the firmware's board image is neither built nor run in QEMU (apt install gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm)"

# The suite runs on TEST_WORKERS pytest-xdist workers: most of a whole-daemon test's time is the arm's
# real time (a rotate, a map), with a core at a time busy, so two cores take several such tests at once.
# A test marked `alone` (franky-sim's, QEMU's, a reinstall of this venv) has the machine to itself
# (tests/conftest.py, cores_shared). TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 3
PYTEST := $(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

test: $(WARM_JIT) lint
	@$(CROSS_TOOLS) || $(NO_CROSS)
	@command -v openscad >/dev/null || $(NO_OPENSCAD)
	$(PYTEST) --durations=20

# the quick tier: the type checker, then pure logic and transports, without the whole-daemon runs
check: $(WARM_JIT) lint
	$(PYTEST) -m "not slow"

# the type checker (mypy, pyproject's [tool.mypy]): every tecdard.* import resolves through the folders
# linked under tecdard/ (tecdard/control -> control/, ...), as the wheel installs them
lint: $(STAMP)
	$(PY) -m mypy

# the soft fingertip (hardware/fingertip/): every part as an STL, each checked closed, and the drawing
# docs/img/fingertip.png; Debian's openscad (.ci/run installs it)
NO_OPENSCAD = echo "make: no openscad here: the fingertip's parts are neither rendered nor checked (apt install openscad)"
fingertip: $(STAMP)
	@command -v openscad >/dev/null || { $(NO_OPENSCAD); exit 1; }
	$(PY) hardware/fingertip/render.py

firmware:
	$(MAKE) -s -C firmware host
	@if $(CROSS_TOOLS); then $(MAKE) -s -C firmware cross; else $(NO_CROSS); fi

bench: $(WARM_JIT)
	$(PIP) install --quiet -e '.[test,ur,viz,bench,franka,franka-sim,ros2,ros2-test,fleet,lerobot,lerobot-test]'
	$(PY) -m benchmarks.estimation
	$(PY) -m benchmarks.serial
	$(PY) -m benchmarks.sim
	$(PY) -m benchmarks
	$(PY) -m benchmarks.mapping
	$(PY) -m benchmarks.hostile
	$(PY) -m benchmarks.ur
	$(PY) -m benchmarks.franka
	$(PY) -m benchmarks.viz
	$(PY) -m benchmarks.mujoco
	$(PY) -m benchmarks.poses
	$(PY) -m benchmarks.onset
	$(PY) -m benchmarks.onset_live
	$(PY) -m benchmarks.trigger_latency
	$(PY) -m benchmarks.wrench_onset
	$(PY) -m benchmarks.recover
	$(PY) -m benchmarks.onset_study
	$(PY) -m benchmarks.robustness
	$(PY) -m benchmarks.robustness --breaking
	$(PY) -m benchmarks.startup --cold
	$(PY) -m benchmarks.firmware
	$(PY) -m benchmarks.ros2
	$(PY) -m benchmarks.ros2_actions
	$(PY) -m benchmarks.figure
	$(PY) -m benchmarks.fleet

clean:
	rm -rf $(VENV) build *.egg-info firmware/build hardware/fingertip/build
