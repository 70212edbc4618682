# Two entry points (see README): `make sim` and `make test`. Both set up .venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-dev sim test lint bench firmware arm-toolchain
FW := firmware_protocol/firmware
ARM_PKGS := gcc-arm-none-eabi libnewlib-arm-none-eabi

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

setup: $(BIN)/python
	$(BIN)/pip install -q -e '.[plot]'

setup-dev: $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'

# the C firmware core as the shared library the simulated truck loads (docs/firmware.md),
# and the identification's C free-run kernel (docs/diagnosis.md)
firmware:
	@$(MAKE) -s -C $(FW) host
	@$(MAKE) -s -C truckd/ident/kernel

# the Cortex-M4 toolchain for the arm build test: installed quietly when missing and we
# may (root with apt, as in CI); otherwise that test fails and names the install command
arm-toolchain:
	@command -v arm-none-eabi-gcc >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing $(ARM_PKGS) (apt-get)"; \
	    { apt-get update -qq >/dev/null && \
	      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(ARM_PKGS) >/dev/null; } || \
	    echo "note: installing $(ARM_PKGS) failed; tests/test_firmware_arm.py will fail" >&2; \
	  else \
	    echo "note: arm-none-eabi-gcc missing; tests/test_firmware_arm.py will fail." \
	      "Install: apt-get install -y $(ARM_PKGS)" >&2; \
	  fi; }

sim: setup firmware
	mkdir -p out
	$(BIN)/truckd sim --scenario all --json out/sim.json --plot out/sim.png

lint: setup-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check truckd tests benchmarks firmware_protocol
	$(BIN)/mypy

test: lint firmware arm-toolchain
	$(BIN)/pytest -q

bench: setup-dev
	$(BIN)/python benchmarks/run_all.py
