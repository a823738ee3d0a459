# Quick start: `make demo` and `make test`. Both create .venv on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint venv clean

$(STAMP): pyproject.toml setup.py
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[station,dev,cluster]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/qnav demo

test: $(STAMP)
	sh tools/install_test_deps.sh
	$(BIN)/ruff check .
	$(BIN)/mypy
	# Unit and in-process tests on both cores (pytest-xdist); the HIL and fault
	# tests time robots, sims and links on the wall clock, so they run one at a
	# time (two at a time, the vcan e-stop and serial-bench tests failed); the
	# Ray tests start their own two-node cluster.
	$(BIN)/python -m pytest -q -n 2 -m "not ray" tests/firmware_py tests/sim_bridge tests/ground_station \
		tests/test_layering.py tests/test_packaging.py tests/test_docs_commands.py
	$(BIN)/python -m pytest -q tests/hil tests/faults
	$(BIN)/python -m pytest -q -m ray tests/ground_station

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info out
