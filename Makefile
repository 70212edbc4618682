# Two entry points (see README): `make sim` and `make test`. Both set up .venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-dev sim test lint bench firmware
FW := firmware_protocol/firmware

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

setup: $(BIN)/python
	$(BIN)/pip install -q -e '.[plot]'

setup-dev: $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'

# the C firmware core as the shared library the simulated truck loads (docs/firmware.md),
# the identification's C free-run kernel (docs/diagnosis.md), and the MPC's compiled cycle
# (OSQP's generated solver; generated with .venv's Python when there is one, docs/controller.md)
firmware:
	@$(MAKE) -s -C $(FW) host
	@$(MAKE) -s -C truckd/ident/kernel
	@$(MAKE) -s -C truckd/control/kernel PY=$(abspath $(BIN)/python)

sim: setup firmware
	mkdir -p out
	$(BIN)/truckd sim --scenario all --json out/sim.json --plot out/sim.png

lint: setup-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check truckd tests benchmarks firmware_protocol
	$(BIN)/mypy

# Installs nothing outside .venv: a test whose tool is missing (arm-none-eabi-gcc,
# systemd-analyze) is skipped with the reason in the summary; .ci/run installs them.
# The tests with real-time processes (marker hil) run at normal priority. Beside them, on
# one worker, run the diagnosis tests (CPU only: no process, no clock) as idle-class work
# (SCHED_IDLE where chrt exists, and nice 19): one core stays free and a real-time process
# that wakes takes the other at once. The other tests follow on both cores. The HIL tests'
# output (out/test-hil.log) comes last.
IDLE := $(shell command -v chrt >/dev/null 2>&1 && echo chrt --idle 0) nice -n 19
BESIDE_HIL := $(wildcard tests/test_diagnose_*.py tests/test_ident_*.py) tests/test_terrain.py \
	tests/test_emps.py tests/test_platoon_diagnosed.py
test: lint firmware
	@mkdir -p out
	@$(BIN)/pytest -q -m hil -p no:cacheprovider >out/test-hil.log 2>&1 & hil=$$!; \
	$(IDLE) $(BIN)/pytest -q -m 'not hil' -p no:cacheprovider $(BESIDE_HIL); a=$$?; \
	wait $$hil; h=$$?; \
	$(BIN)/pytest -q -m 'not hil' -n 2 --dist loadfile $(addprefix --ignore=,$(BESIDE_HIL)); b=$$?; \
	echo "--- HIL tests (real-time processes, out/test-hil.log)"; cat out/test-hil.log; \
	test $$a -eq 0 -a $$b -eq 0 -a $$h -eq 0

bench: setup-dev
	$(BIN)/python benchmarks/run_all.py
