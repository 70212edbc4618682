# Two entry points (see README): `make sim` and `make test`. Both set up .venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-dev sim test lint bench firmware
FW := firmware_protocol/firmware

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Installed once per change of pyproject.toml (the stamp files in .venv): a second
# `make sim` or `make test` reinstalls nothing, and needs no package index.
setup: $(VENV)/.installed-plot
setup-dev: $(VENV)/.installed-dev

$(VENV)/.installed-plot: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[plot]'
	@touch $@

$(VENV)/.installed-dev: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'
	@touch $@

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
# The tests without real-time processes run on both cores; then the tests with real-time
# processes (marker hil), two files at a time (mostly waiting on real time); then those
# that load the machine by design or measure timing (marker alone: the plan flood,
# characterize's drives), with nothing beside them.
test: lint firmware
	$(BIN)/pytest -q -m 'not hil' -n 2 --dist loadfile
	$(BIN)/pytest -q -m 'hil and not alone' -n 2 --dist loadfile
	$(BIN)/pytest -q -m alone

bench: setup-dev
	$(BIN)/pip install -q -e '.[dev,bench]'
	$(BIN)/python benchmarks/run_all.py
