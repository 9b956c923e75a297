# torsoscan: two commands on a fresh machine.
#   make demo   creates .venv, installs, runs the main job on the embedded default
#   make test   creates .venv, installs, runs the whole suite
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SYSDEPS := libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 chromium nginx-light

.PHONY: demo test venv sysdeps bench faults clean

DEMO := demo-out
# What a clinic does, on the embedded default (SQLite under var/, jobs in-process):
# a reduced rig calibrated, a patient with a baseline, a re-scan and a follow-up,
# all through the API; then `DEBUG=true .venv/bin/python manage.py runserver` shows the pages.
demo: export DEBUG = true
demo: $(STAMP)
	$(PY) manage.py migrate --noinput
	$(PY) manage.py demo --out $(DEMO) --seed 11

# The suite in TEST_WORKERS processes (pytest-xdist), each test file whole in one of them, the costliest
# files first (tests/conftest.py); the tiny scenarios are simulated once for all. One worker more than the
# cores: the service tests spend part of their time waiting on their servers, workers and browser, and a
# third worker fills those gaps (2 cores: 907 s with two workers, 768 s with three). The slowest tests are
# listed at the end.
TEST_WORKERS ?= $(shell echo $$(( $$(nproc 2>/dev/null || echo 1) + 1 )))
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=15 tests

venv: $(STAMP)

# System libraries that open3d loads (libusb; its rendering module, GL/EGL); Chromium for the browser test;
# nginx for the slow-client test (the compose file's front door).
sysdeps:
	@missing=""; for p in $(SYSDEPS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then \
		echo "missing system packages:$$missing (install them as root with apt-get)"; exit 0; fi; \
	echo "installing system packages:$$missing"; \
	apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null

$(STAMP): pyproject.toml | sysdeps
	@command -v uv >/dev/null 2>&1 || $(PYTHON) -m pip install -q uv || true
	@if command -v uv >/dev/null 2>&1; then \
		[ -x $(PY) ] || uv venv -q $(VENV); \
		uv pip install -q -p $(PY) -e ".[test]"; \
	else \
		[ -x $(PY) ] || $(PYTHON) -m venv $(VENV); \
		$(PY) -m pip install -q -e ".[test]"; \
	fi
	@# the matching's kernels compiled once (numba, about 24 s), not by every process that first matches
	$(PY) -c "from recon_engine.kernels import warm_up; warm_up()"
	@touch $(STAMP)

# The paper-scale figures of docs/benchmarks.md (hours on 2 cores).
bench: $(STAMP)
	@if command -v uv >/dev/null 2>&1; then uv pip install -q -p $(PY) -e ".[bench,server]"; else $(PY) -m pip install -q -e ".[bench,server]"; fi
	$(PY) benchmarks/bench_simulate.py --preset paper --out bench-out/paper
	$(PY) benchmarks/bench_calibrate.py --scenario bench-out/paper
	$(PY) benchmarks/bench_epipolar.py --scenario bench-out/paper --capture visit0-a
	$(PY) benchmarks/bench_matching_kernels.py --reference 43bb649
	$(PY) benchmarks/bench_reconstruct_arm.py --scenario bench-out/paper --capture visit0-a
	$(PY) benchmarks/bench_reconstruct.py --scenario bench-out/paper --capture visit0-a visit0-b visit1-a
	$(PY) benchmarks/bench_service.py --scenario bench-out/paper --capture visit0-a

# Faults injected into a running clinic (needs PostgreSQL on 127.0.0.1:5432 and redis-server; about 15 min):
# the broker stopped, workers and pool children killed, database connections cut. Prints, per scenario,
# jobs completed / lost / stuck and files orphaned / missing (docs/operations.md); exits 1 unless all zero.
faults: $(STAMP)
	$(PY) benchmarks/bench_faults.py

clean:
	rm -rf $(VENV) demo-out bench-out var .pytest_cache
