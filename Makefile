# fftune: top-level targets. `make demo` and `make test` need nothing else on a fresh
# Debian machine with python3 (+ python3-venv) and a C compiler.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV   := .venv
PY     := $(CURDIR)/$(VENV)/bin/python
STAMP  := $(VENV)/.installed
FW     := $(MAKE) --no-print-directory -C firmware_sim PYTHON=$(PY)

.PHONY: help setup firmware demo demo-machine demo-track paper test bench cross pil pil-run fuzz system-deps clean mutation

help:
	@echo "make setup        venv (.venv) with pinned deps + firmware_sim build (other targets do it)"
	@echo "make demo         the main job on the simulated drive (writes out/demo/)"
	@echo "make demo-machine a simulated 4-axis machine on one 1 Mbit/s bus, every axis tuned at once (out/machine_demo/)"
	@echo "make paper        the paper's results reproduced side by side (out/paper/: report.html, paper-reproduction.md)"
	@echo "make demo-track   K_fc tracked from the repeated task on a drifting simulated plant (writes out/demo-track/)"
	@echo "make test         every test, C and Python (parallel: TEST_WORKERS=2 per core; prints its wall time)"
	@echo "make bench        benchmarks, printing their figures"
	@echo "make cross        deployable C for Cortex-M4F (arm-none-eabi-gcc), with sizes"
	@echo "make pil          the drive for an STM32F405 (Cortex-M4F, qemu netduinoplus2) with configs/pil.yaml's plant, with sizes"
	@echo "make pil-run      pil + start it in qemu-system-arm; prints its SLCAN channel (socket://127.0.0.1:PORT)"
	@echo "make mutation     mutation testing (C harness + cosmic-ray), scores per module; long, resumable"
	@echo "make system-deps  (root) optional Debian packages: qemu, kernel, arm gcc, clang, can-utils, valgrind, octave (+ control), chromium"
	@echo "make clean"

setup: $(STAMP) firmware

# A first run prints one line for the venv and one for the C build; their full output goes
# to build/setup-pip.log and build/firmware.log, printed only when they fail.
$(STAMP): pyproject.toml requirements.lock
	@$(PYTHON) -c 'import ensurepip, venv' 2>/dev/null || { echo "make setup: python3 venv support missing: apt-get install python3-venv" >&2; exit 1; }
	@mkdir -p build; log=build/setup-pip.log; start=$$(date +%s); \
	if { $(PYTHON) -m venv $(VENV) && \
	     $(VENV)/bin/python -m pip install -q --disable-pip-version-check -r requirements.lock && \
	     $(VENV)/bin/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e . ; } >$$log 2>&1; then \
	    echo "make setup: .venv with the pinned dependencies in $$(( $$(date +%s) - start )) s (log: $$log)"; \
	else rc=$$?; cat $$log >&2; echo "make setup: pip failed with status $$rc (output above, kept in $$log)" >&2; exit $$rc; fi
	@touch $@

firmware: $(STAMP)
	@mkdir -p build; log=build/firmware.log; start=$$(date +%s); \
	if $(FW) all >$$log 2>&1; then \
	    [ -s $$log ] && echo "make setup: firmware_sim built, $$(grep -c -- '-o ' $$log) targets in $$(( $$(date +%s) - start )) s (log: $$log)"; true; \
	else rc=$$?; cat $$log >&2; echo "make setup: the firmware_sim build failed with status $$rc (output above, kept in $$log)" >&2; exit $$rc; fi

demo: setup
	@$(VENV)/bin/fftune demo

demo-machine: setup
	@$(VENV)/bin/fftune demo --machine configs/machine_demo.yaml

# The paper's results beside the measured ones: out/paper/reproduction.json, figures, report
# and out/paper/paper-reproduction.md (the docs page's table, from its template; the tracked
# docs/paper-reproduction.md is only written on purpose: `fftune paper --doc docs/...`).
paper: setup
	@$(VENV)/bin/fftune paper --no-progress --doc out/paper/paper-reproduction.md \
	    --template docs/paper-reproduction.template.md

# friction tracking from the repeated task on a drifting simulated plant (docs/track.md)
demo-track: setup
	@$(VENV)/bin/fftune demo-track

# pytest-xdist workers: two per core (at most 16). Many tests wait on a real-time drive_sim,
# a heartbeat or a qemu guest; with one worker per core a quiet 2-core machine was busy
# 141 % of `make test`'s 360 s, with two per core 188 % of 269 s (2026-11-27).
# --dist loadgroup keeps the tests that share one qemu guest boot or firmware_sim build
# outputs on one worker (tests/conftest.py).
TEST_WORKERS ?= $(shell n=$$(( $$(nproc) * 2 )); [ $$n -gt 16 ] && n=16; echo $$n)

test: setup
	@start=$$(date +%s); rc=0; \
	$(FW) -j$$(nproc) test-build >/dev/null || rc=$$?; \
	[ $$rc = 0 ] && { $(FW) test || rc=$$?; }; \
	if [ $$rc = 0 ]; then \
	    $(VENV)/bin/python -m pytest -q -ra -n $(TEST_WORKERS) --dist loadgroup tests || rc=$$?; fi; \
	echo "make test: wall time $$(( $$(date +%s) - start )) s (load average $$(cut -d' ' -f1-3 /proc/loadavg)), exit status $$rc"; \
	exit $$rc

bench: setup
	@echo "== make bench: load average $$(cut -d' ' -f1-3 /proc/loadavg) on $$(nproc) cores (figures on a loaded machine are pessimistic)"
	@$(FW) bench
	@set -e; for b in tests/bench/bench_*.py; do [ -e "$$b" ] || continue; echo "== $$b"; $(VENV)/bin/python "$$b"; done
	@echo "== tests/bench/bench_canopen.py over vcan0 in the qemu guest (software emulation: slow)"
	@# informational (Python under TCG is 10-40x slower): a failure there is reported, not fatal
	@if $(PY) tests/vm/guest.py check >/dev/null 2>&1; then \
	    $(PY) tests/vm/guest.py run --timeout 400 --env FFTUNE_TEST_CAN=socketcan:vcan0 -- \
	        $(PY) tests/bench/bench_canopen.py \
	    || echo "qemu/vcan0 part: FAILED with status $$? (output above); its figures are missing, the host's above stand"; \
	else echo "skipped: $$($(PY) tests/vm/guest.py check 2>&1 | tail -1)"; fi
	@echo "== make bench: done; load average $$(cut -d' ' -f1-3 /proc/loadavg)"

cross:
	@command -v arm-none-eabi-gcc >/dev/null 2>&1 || { echo "make cross: arm-none-eabi-gcc not found (install: sudo make system-deps, package gcc-arm-none-eabi)" >&2; exit 1; }
	@$(MAKE) --no-print-directory -C firmware_sim cross PYTHON=$(PYTHON)

pil: setup
	@command -v arm-none-eabi-gcc >/dev/null 2>&1 || { echo "make pil: arm-none-eabi-gcc not found (install: sudo make system-deps, packages gcc-arm-none-eabi libnewlib-arm-none-eabi)" >&2; exit 1; }
	@$(FW) pil

pil-run: pil
	@$(PY) firmware_sim/port/mcu/pil_run.py

fuzz: setup
	@$(FW) fuzz

# Mutation testing (docs/testing.md): the deployable C with tools/mutation/cmut.py, the
# analysis package with cosmic-ray (pinned in tools/mutation/requirements.txt, installed
# into .venv here). Each half runs at most MUTATION_BUDGET seconds; results are kept in
# build/mutation/ and the next call continues with the mutants not run yet.
MUTATION_BUDGET ?= 3600
# MUTATION_MODULES="canopen/co_sdo.c analysis/bla.py": only these modules (default: all)
MUTATION_MODULES ?=
MUTATION_ONLY = $(if $(strip $(MUTATION_MODULES)),--modules "$(MUTATION_MODULES)")
mutation: setup $(VENV)/.mutation-tools
	@$(PY) tools/mutation/cmut.py --budget $(MUTATION_BUDGET) $(MUTATION_ONLY)
	@echo
	@$(PY) tools/mutation/pymut.py --budget $(MUTATION_BUDGET) $(MUTATION_ONLY)

$(VENV)/.mutation-tools: tools/mutation/requirements.txt $(STAMP)
	$(VENV)/bin/python -m pip install -q --disable-pip-version-check -r tools/mutation/requirements.txt
	@touch $@

system-deps:
	@[ "$$(id -u)" = 0 ] || { echo "make system-deps: must run as root (uses apt-get)" >&2; exit 1; }
	@command -v apt-get >/dev/null || { echo "make system-deps: needs a Debian/Ubuntu system (apt-get)" >&2; exit 1; }
	apt-get update -qq
	DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
	    python3-venv gcc make gcc-arm-none-eabi libnewlib-arm-none-eabi \
	    qemu-system-x86 qemu-system-arm linux-image-amd64 busybox-static cpio kmod \
	    can-utils clang llvm libclang-rt-14-dev valgrind octave octave-control chromium >/dev/null

clean:
	@$(MAKE) --no-print-directory -C firmware_sim clean
	rm -rf $(VENV) out build .pytest_cache *.egg-info
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
