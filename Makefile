# UltraStage pipeline. `make dataset` and `make test` work on a fresh machine: `setup` installs everything.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
RUN ?= runs/default
ARGS ?=
# Free disk (GiB) a fresh `make setup` asks for before it creates the environment.
SETUP_FREE_GIB ?= 4

.PHONY: setup dataset test bench bench-full bench-quick panel lint clean-runs compat

setup: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	@# A fresh environment takes about 3 GiB (torch, open3d); a full disk would stop apt or pip halfway with an OSError.
	@test -x $(PY) || $(PYTHON) -c 'import os, shutil, sys; need = float(sys.argv[1]); \
	  free = shutil.disk_usage(".").free / 2**30; sys.exit(0 if free >= need else \
	  f"setup: {free:.1f} GiB free on the disk of {os.getcwd()}, and the environment ($(VENV)) needs about {need:g} GiB: " \
	  "free some space and run make again")' $(SETUP_FREE_GIB)
	@# open3d needs libusb-1.0 at import time (a Debian package).
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0; \
	  else echo "setup: libusb-1.0-0 is missing; install it (sudo apt-get install libusb-1.0-0)" >&2; exit 1; fi; fi
	@# The release page's test loads index.html in a headless browser: Debian's chromium.
	@if ! command -v chromium >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "setup: chromium is missing; the release page test skips without it (sudo apt-get install chromium)" >&2; fi; fi
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@# pip compiles the packages' bytecode one file after another; compileall does it on every core (22 s less of an
	@# 80 s install on 2 cores). The bytecode is needed: this environment sets PYTHONDONTWRITEBYTECODE, so a module
	@# without it is compiled again at every import. torch ships one test file in Python 3.12 syntax.
	$(PY) -m pip install -q --no-compile -r requirements.lock
	$(PY) -m compileall -q -j 0 -x 'torch/testing/_internal/py312_intrinsics' $(VENV)/lib
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

# Simulate the embedded default capture (skipped when it is already there with the same settings),
# run the whole DAG, publish the release and print the summary with accuracy against ground truth.
dataset: setup
	$(VENV)/bin/ultrastage simulate --out $(RUN)/capture
	$(VENV)/bin/ultrastage run --capture $(RUN)/capture --release $(RUN)/release $(ARGS)

# The suite on TEST_WORKERS pytest-xdist workers (one per core by default), a test file per worker at a time, so
# the fixtures a file's tests share are built once; TEST_WORKERS=0 runs it in this one process.
TEST_WORKERS ?= auto
test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The slowest benches smaller than their own defaults (bench/run_all.py MAKE_BENCH_ARGS): under 45 minutes on 2 cores.
bench: setup
	$(PY) bench/run_all.py --out bench/out

# Every bench at its own full size (2,000-action engine runs, production-size memory, both passes' full sweeps).
bench-full: setup
	$(PY) bench/run_all.py --full --out bench/out

# The subject panel (bench/bench_subjects.py): ten one-action captures at the default width (MakeHuman bodies at the
# extremes of its macro targets, posed, with hair, in a skirt; the ICT head and the procedural subject), each through
# the whole pipeline and its evaluation, one at a time; the table per subject and the worst cases go to bench/out
# (bench_subjects.md / .json / .png). Then the panel's relighting set: AlbedoNet and NormalNet trained on the panel's
# subjects and on make dataset's one body, measured on the same held-out subjects (bench_panel_set.md / .json).
# Part of `make bench-full`, not of `make bench` (too long for its 45 minutes).
panel: setup
	nice -n 10 $(PY) bench/bench_subjects.py --out bench/out
	nice -n 10 $(PY) bench/bench_panel_set.py --out bench/out

# Every bench on the smallest inputs that run its code (the tests run it too): checks, not measurements. Two lanes:
# the benches that read the shared tiny run one after another, the others beside them.
bench-quick: setup
	$(PY) bench/run_all.py --quick --lanes 2 --out bench/out-quick

# Other tools' own loaders on a release (nerfstudio's dataparsers, COLMAP's reader), in their own environment
# .venv-compat (never the main one). torch 2.13.0 goes in first from the CPU build the machine's pip finds
# (https://download.pytorch.org/whl/cpu, or TORCH_CPU_INDEX= where pip's find-links already holds the CPU wheel),
# so nerfstudio's requirement is already met and pip pulls no CUDA wheels (checked below). Needs a release:
# `make dataset` first (or RUN=...).
COMPAT_VENV := .venv-compat
COMPAT_STAMP := $(COMPAT_VENV)/.installed
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu

$(COMPAT_STAMP):
	test -x $(COMPAT_VENV)/bin/python || $(PYTHON) -m venv $(COMPAT_VENV)
	$(COMPAT_VENV)/bin/python -m pip install -q --upgrade pip
	$(COMPAT_VENV)/bin/python -m pip install -q torch==2.13.0 $(if $(TORCH_CPU_INDEX),--extra-index-url $(TORCH_CPU_INDEX))
	$(COMPAT_VENV)/bin/python -m pip install -q nerfstudio==1.1.5 torch==2.13.0 $(if $(TORCH_CPU_INDEX),--extra-index-url $(TORCH_CPU_INDEX))
	@if $(COMPAT_VENV)/bin/python -m pip list 2>/dev/null | grep -qi '^nvidia-'; then \
	  echo "compat: CUDA wheels were pulled into $(COMPAT_VENV); remove it and check the torch index" >&2; exit 1; fi
	touch $(COMPAT_STAMP)

compat: $(COMPAT_STAMP)
	$(COMPAT_VENV)/bin/python tests/compat/check_release.py $(RUN)/release

lint: setup
	$(PY) -m compileall -q pipeline artifacts stages manifests calibration synthetic evaluation ultrastage

clean-runs:
	rm -rf runs
