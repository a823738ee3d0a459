# Quick start: `make demo` and `make test`. Both create .venv on first use.
PY ?= python3
# Let Python write its bytecode caches (__pycache__/, git-ignored) even where the environment sets
# PYTHONDONTWRITEBYTECODE=1 (these machines do): then every process compiles every module it imports,
# and make test starts hundreds (measured: importing ray.tune, numba, pymavlink and numpy 4.7 s of CPU
# per process, 1.6 s from the caches; the robot's, sim's and station's own modules 1.6 s -> 0.5 s).
export PYTHONDONTWRITEBYTECODE :=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check lint venv clean

$(STAMP): pyproject.toml setup.py
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	# uv installs the same packages as pip (same resolution from pyproject.toml: compared with
	# `pip freeze`) in a third of the time (fresh venv: 66 s -> 17 s here); pip if uv cannot be had
	$(BIN)/python -m pip install --quiet uv && \
	  $(BIN)/uv pip install --quiet --python $(BIN)/python -e '.[station,dev,cluster]' || { \
	  $(BIN)/python -m pip install --quiet --upgrade pip && \
	  $(BIN)/python -m pip install --quiet -e '.[station,dev,cluster]'; }
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/qnav demo

test: $(STAMP)
	# numba's cache filled once (tools/warm_numba.py) in the background, beside the
	# Debian test packages and UML check, ruff and mypy: otherwise every xdist worker
	# and every `qnav` process a test starts compiles the same kernels.
	# The Debian packages (apt, downloads: mostly waiting) beside ruff and mypy (38 s of CPU).
	$(BIN)/python tools/warm_numba.py --quiet & warm=$$!; \
	sh tools/install_test_deps.sh & deps=$$!; \
	$(BIN)/ruff check . && $(BIN)/mypy; status=$$?; \
	wait $$deps || status=1; wait $$warm || status=1; exit $$status
	# Everything but the wall-clock tests on four pytest-xdist workers (at two,
	# the 2 cores were busy 58 % of the run: many tests wait on processes and
	# sockets; three -> four: 6:07 -> 5:32 on a fresh clone, 169 % CPU), grouped
	# tests on one worker each (xdist_group: the Ray cluster, the
	# UML vcan batch); then the tests judged on the wall clock (marker `wallclock`:
	# real-time sims under MAVSDK, floods and link timing against the control tick),
	# four at a time, one test handed out at a time (longest first: conftest.py): paced sims
	# mostly wait (the pass keeps under a core busy), and they must hold beside other work
	# anyway (13 passed in 38 s; 46 s at three, in batches; 50 s beside two busy loops).
	$(BIN)/python -m pytest -q --durations=15 -n 4 --dist loadgroup -m "not wallclock" tests/firmware_py tests/sim_bridge \
		tests/ground_station tests/hil tests/faults tests/test_layering.py tests/test_packaging.py \
		tests/test_docs_commands.py
	$(BIN)/python -m pytest -q --durations=15 -n 4 --maxschedchunk 1 -m wallclock tests/hil tests/faults \
		tests/firmware_py/test_runtime_isolation.py

# The inner loop (under a minute): lint, types and the robot's and the sim's in-process tests
# (pure cores, the controller and MAVLink engines on python-can's virtual bus; no HIL processes,
# no wall-clock judgement). `make test` stays the whole suite and the CI command.
check: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 -p no:cacheprovider -m "not slow and not wallclock and not ray and not vcan" \
		tests/firmware_py tests/sim_bridge tests/test_layering.py

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info out .numba_cache
