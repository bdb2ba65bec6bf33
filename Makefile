# tecdar: `make run` (demo on the simulated robot), `make test`, `make bench`.
PY_BOOT ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install run test bench clean

$(PY):
	$(PY_BOOT) -m venv $(VENV)

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(PY) -m tecdard demo --config configs/sim.yaml

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[test,bench]'
	$(PY) -m benchmarks.estimation
	$(PY) -m benchmarks.serial
	$(PY) -m benchmarks.sim
	$(PY) -m benchmarks
	$(PY) -m benchmarks.mapping
	$(PY) -m benchmarks.hostile

clean:
	rm -rf $(VENV) build *.egg-info
