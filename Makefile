# ptm_ros — two commands on a fresh machine: `make demo` and `make test` (see README.md).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
DEMO_BAG ?= bags/demo
DEMO_OUT ?= out/demo
DEMO_PARAMS ?= config/demo.yaml

# DDS for tests and the demo: localhost only, a per-run domain, fast discovery announcements.
ROS_ENV = AMENT_PREFIX_PATH=$(abspath $(VENV)) \
	OPENBLAS_NUM_THREADS=$${OPENBLAS_NUM_THREADS:-1} \
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST \
	ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-$$(( $$$$ % 200 + 20 ))} \
	FASTDDS_DEFAULT_PROFILES_FILE=$(abspath config/fastdds.xml) \
	RMW_IMPLEMENTATION=rmw_fastrtps_cpp

.PHONY: demo test check bench install lint clean

$(VENV): requirements.txt
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q -r requirements.txt
	touch $(VENV)

# Reinstall the package itself (not its dependencies) so console scripts and share/ are current.
install: $(VENV)
	$(PIP) install -q --no-deps --no-build-isolation .

# Tests that do not use DDS run on PYTEST_WORKERS processes (pytest-xdist, one per core by default);
# the DDS tests (marker dds: rclpy nodes, child processes, per-test domains, a domain range per worker) run
# after them, on as many workers.
PYTEST_WORKERS ?= auto

# The whole suite, after the lint (formatting, ruff, the import layers of .importlinter, mypy.ini's types).
test: lint install
	$(ROS_ENV) $(PY) -m pytest -q -p no:cacheprovider --durations=15 -n $(PYTEST_WORKERS) -m "not dds" test
	$(ROS_ENV) $(PY) -m pytest -q -p no:cacheprovider --durations=15 -n $(PYTEST_WORKERS) -m dds test

# The fast subset, after the lint: no test marked slow (many seconds) or dds (rclpy nodes over DDS).
check: lint install
	$(ROS_ENV) $(PY) -m pytest -q -p no:cacheprovider -n $(PYTEST_WORKERS) -m "not slow and not dds" test

# The node suite over DDS on the bundled bag (separate processes, launch-free), then the score.
demo: install
	$(ROS_ENV) $(VENV)/bin/ptm-bringup --bag $(DEMO_BAG) --rate 0 --params $(DEMO_PARAMS) --out $(DEMO_OUT)

bench: install
	$(ROS_ENV) $(PY) bench/run_all.py

lint: $(VENV)
	$(VENV)/bin/ruff check ptm_ros test bench
	$(VENV)/bin/ruff format --check ptm_ros test bench
	$(VENV)/bin/lint-imports --no-cache
	$(VENV)/bin/mypy

clean:
	rm -rf build *.egg-info out .pytest_cache .mypy_cache
