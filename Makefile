# Two entry points (see README): `make sim` and `make test`. Both set up .venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-dev sim test lint bench

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

setup: $(BIN)/python
	$(BIN)/pip install -q -e '.[plot]'

setup-dev: $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'

sim: setup
	mkdir -p out
	$(BIN)/truckd sim --scenario all --json out/sim.json --plot out/sim.png

lint: setup-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check truckd tests benchmarks firmware_protocol
	$(BIN)/mypy

test: lint
	$(BIN)/pytest -q

bench: setup-dev
	$(BIN)/python benchmarks/run_all.py
