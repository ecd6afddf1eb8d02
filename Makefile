# Every target builds (once) and reuses the project's own virtual environment.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
CONFIG ?= config/sim.toml

INSTALL_PYTHON ?= /usr/bin/python3

.PHONY: run test docs test-slow bench bench-modbus lint clean install constraints systemd-deps device-deps test-systemd

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) (apt-get install python3 python3-venv)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/leveler run --config $(CONFIG)

# Two pytest-xdist workers a core, a test file to a worker so its module fixtures are made
# once: many tests wait on a daemon, a socket or a pty, and a second worker fills the core
# meanwhile (2 cores, 2026-12-02: 355 s with 4 workers, 480 s with 2, 692 s of CPU in all).
# One BLAS thread per worker: the workers already fill the cores.
TEST_WORKERS ?= $(shell echo $$(( 2 * $$(nproc) )))
test: $(STAMP) device-deps
	$(BIN)/ruff check .
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 \
	  $(BIN)/python -m pytest -q -m "not slow and not systemd" -n $(TEST_WORKERS) --dist loadfile

# Every `$ ...` transcript in README.md and docs/*.md rerun and rewritten (docs/examples.py,
# about a minute); make test fails when one drifts beyond its stated tolerance.
docs: $(STAMP)
	$(BIN)/python docs/examples.py

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

# The property tests with fresh random examples (make test draws the same ones every run).
# Repeat it to hunt; a failure prints the @reproduce_failure line that replays it.
.PHONY: test-explore
test-explore: $(STAMP)
	HYPOTHESIS_PROFILE=explore $(BIN)/python -m pytest -q -m "not slow and not systemd" \
	  $$(grep -l '^from hypothesis' tests/*.py)

# The bench's extra dependency (simple-pid, the PID baseline), its own stamp.
BENCH_STAMP := $(VENV)/.bench-installed
$(BENCH_STAMP): $(STAMP) pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(BENCH_STAMP)

# One table of every figure beside its baseline, also bench/results.json (docs/performance.md):
# 10-12 minutes on 2 cores. `make bench-quick` (or `make bench ARGS=--quick`): under 2.
# ARGS go to bench/run.py, e.g. ARGS="--quick --only sim_speed,pid_speed".
bench: $(BENCH_STAMP)
	$(BIN)/python bench/run.py $(ARGS)

.PHONY: bench-quick
bench-quick: $(BENCH_STAMP)
	$(BIN)/python bench/run.py --quick $(ARGS)

# `leveler diagnose` scored on logs of the independent generator (bench/independent/):
# confusion matrix, false alarms on nulls, per-severity hits; JSON to /tmp/diagnose-score.json.
# Hours on 2 cores; ARGS="--quick" takes 10-20 min. ARGS="--untouched": the report-only seeds.
.PHONY: bench-diagnose
bench-diagnose: $(STAMP)
	$(BIN)/python bench/diagnose_score.py $(ARGS)

# 100 Hz over Modbus TCP on loopback for 10 minutes, after cyclictest at 100 Hz (the OS limit)
# and the sim backend (the baseline), each as long: 30 min.
bench-modbus: $(STAMP)
	$(BIN)/python bench/modbus_loop.py 600

# Issue 8's soak: the daemon's real-time loop at 1 kHz with logging on for an hour (as root:
# SCHED_FIFO + mlockall as the service), next to cyclictest (10 min), with its RSS growth:
# about 72 minutes. Shorter: `$(BIN)/python bench/loop_timing.py --duration SECONDS`.
.PHONY: bench-soak
bench-soak: $(STAMP)
	$(BIN)/python bench/loop_timing.py --duration 3600

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info

# The hardened service: system user, /opt/leveler venv, /etc/leveler/leveler.toml (kept if
# present), /etc/systemd/system/leveler.service. Needs root; safe to repeat.
install:
	$(INSTALL_PYTHON) -m leveler.daemon.install --python $(INSTALL_PYTHON)

# The versions make install pins (config/constraints.txt): this venv's, after make test passed.
constraints: $(STAMP)
	{ echo "# The versions make install pins under /opt/leveler: those make test last passed with"; \
	  echo "# (written by make constraints from the dev venv; pip install -c reads it)."; \
	  $(BIN)/python -m pip freeze --exclude-editable; } > config/constraints.txt

# mbpoll: a third-party Modbus client the tests check the emulator with; apt-installed only
# when missing and we are root (elsewhere that test skips and says why).
device-deps:
	@if command -v mbpoll >/dev/null; then :; \
	elif [ "$$(id -u)" -eq 0 ]; then \
	  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mbpoll; } \
	    || echo "could not install mbpoll: the third-party Modbus client test will skip"; \
	else echo "mbpoll missing (sudo apt-get install mbpoll): its test will skip"; fi

# systemd-analyze and systemd-nspawn: apt-installed only when missing and we are root.
systemd-deps:
	@if command -v systemd-analyze >/dev/null && command -v systemd-nspawn >/dev/null; then :; \
	elif [ "$$(id -u)" -eq 0 ]; then \
	  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq systemd systemd-container; } \
	    || echo "could not install systemd-container: the container tests will skip"; \
	else echo "need systemd-analyze and systemd-nspawn: sudo apt-get install systemd systemd-container"; fi

# The unit judged by systemd's own tools, then booted in a container (root; about a minute).
test-systemd: $(STAMP) systemd-deps
	$(BIN)/python -m pytest -q tests/test_systemd_unit.py tests/integration
