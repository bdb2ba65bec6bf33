# tecdar: `make run` (demo on the simulated robot), `make test`, `make check` (quick tier), `make bench`.
PY_BOOT ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# the estimator's compiled kernels in numba's cache: a first start then loads them (~1.5 s)
# instead of compiling them (~60 s on 2 cores)
WARM := $(VENV)/.warm

.PHONY: install run test check bench clean

$(PY):
	$(PY_BOOT) -m venv $(VENV)

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,ur,viz,bench,franka,franka-sim]'
	touch $(STAMP)

$(WARM): $(STAMP) $(wildcard control/estimators/kernels/*.py)
	$(PY) -m tecdard warm
	touch $(WARM)

# a rig's install: the daemon with the arms' clients and the viewers, none of the test, bench or
# simulator extras (`make run` and `make test` install those into the same .venv when asked)
install: $(PY)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[ur,franka,viz]'
	$(PY) -m tecdard warm

run: $(WARM)
	$(PY) -m tecdard demo --config configs/sim.yaml

test: $(WARM)
	$(PY) -m pytest -q

# the quick tier: pure logic and transports, without the whole-daemon runs (under 2 minutes)
check: $(WARM)
	$(PY) -m pytest -q -m "not slow"

bench: $(WARM)
	$(PY) -m pip install --quiet -e '.[test,ur,viz,bench,franka,franka-sim]'
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
	$(PY) -m benchmarks.onset_study
	$(PY) -m benchmarks.startup --cold
	$(PY) -m benchmarks.figure

clean:
	rm -rf $(VENV) build *.egg-info
