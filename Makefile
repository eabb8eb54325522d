# hapticrom: one venv (.venv, Python 3.12), meshes under meshes/, caches under .cache/.
#   make help   the targets, one line each (a target's line is the `## ` comment after it)
#   make demo   set up everything, train the default cornea model on 2 ranks, play it,
#               check it at held-out positions, write the report (out/report/report.html),
#               cut it with the scalpel (latency, and against the full order with the cut meshed)
#   make test   set up everything, then run the tests serially and under mpirun -n 2

SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
NP ?= 2
STAMP := $(VENV)/.installed

# Python 3.12 (the DOLFINx wheel needs >= 3.12): python3.12 on PATH, else under
# pyenv. Each candidate must really run (a pyenv shim without a selected version
# does not).
PYTHON312 ?= $(shell for c in $$(command -v python3.12) $$(ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.12*/bin/python3.12 2>/dev/null | sort -V -r); do \
  "$$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null && { echo "$$c"; break; }; done)

# Caches inside the project: FFCx/DOLFINx JIT (XDG_CACHE_HOME), numba, and no
# writes to $HOME from gmsh or matplotlib.
export XDG_CACHE_HOME := $(CURDIR)/.cache
export NUMBA_CACHE_DIR := $(CURDIR)/.cache/numba
export MPLCONFIGDIR := $(CURDIR)/.cache/matplotlib
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1

DEFAULT_MESHES := meshes/cornea.msh meshes/beam.msh meshes/hemisphere.msh meshes/liver.msh

.PHONY: help venv meshes test test-serial test-mpi test-slow demo bench lint clean docker-test \
  capi capi-asan capi-bench

venv: $(STAMP) ## create .venv and install hapticrom with the offline and test extras

help: ## list the targets, one line each
	@awk 'BEGIN { FS = ":.*## " } /^[a-zA-Z_-]+:.*## / { printf "  make %-12s %s\n", $$1, $$2 }' \
	  $(MAKEFILE_LIST)

$(STAMP): pyproject.toml constraints.txt
	@if [ -z "$(PYTHON312)" ]; then \
	  echo "error: Python 3.12 not found (looked for python3.12 on PATH and under pyenv);" \
	       "install it (e.g. pyenv install 3.12) or run: make PYTHON312=/path/to/python3.12 ..." >&2; \
	  exit 1; fi
	@echo "using $(PYTHON312)"
	$(PYTHON312) -m venv $(VENV)
	$(PY) -m pip install --quiet --constraint constraints.txt --upgrade pip
	$(PY) -m pip install --quiet --constraint constraints.txt --build-constraint constraints.txt -e '.[offline,test]'
	@touch $@

meshes/liver-4k.msh: $(STAMP) ## the liver at 4,117 nodes (examples/liver-4k-campaign.toml)
	$(VENV)/bin/hapticrom mesh liver --set mesh_size=6.4 --out $@

meshes/cornea-coarse.msh: $(STAMP) ## the coarse cornea (examples/cornea-coarse-soft-tip.toml)
	$(VENV)/bin/hapticrom mesh cornea --refinement coarse --out $@

meshes/%.msh: $(STAMP)
	$(VENV)/bin/hapticrom mesh $* --out $@

meshes: $(DEFAULT_MESHES) ## generate the default meshes (cornea, beam, hemisphere, liver)

test: lint capi test-serial test-mpi ## lint, build the C ABI, then the tests serially and under mpirun -n NP (default 2)

# Two workers (pytest-xdist) on the two cores; they share the JIT caches (tests/conftest.py).
test-serial: venv ## the tests that run on one process, NP of them at a time
	$(PY) -m pytest -m "not mpi" -q -n $(NP) tests

test-mpi: venv ## the MPI tests under mpirun -n NP (not the slow ones: see test-slow)
	$(VENV)/bin/mpirun -n $(NP) $(PY) -m pytest -m "mpi and not slow" -q -p no:cacheprovider tests

# Minutes each, not part of `make test` (CI's budget): Q1/P0 against Taylor-Hood on the
# default cornea mesh, 190k unknowns (2 min on 2 cores; the coarse mesh's locking test
# runs in `make test`).
test-slow: venv ## the slow tests (marker slow) under mpirun -n NP
	$(VENV)/bin/mpirun -n $(NP) $(PY) -m pytest -m slow -q -p no:cacheprovider tests

# The campaign resumes: a second `make demo` reuses the stored solves. The default model is
# the soft-tip cornea (force control under a smooth pressure bump): its response varies
# smoothly with the tool position, unlike the rigid tip's node set (see README).
DEMO_CAMPAIGN ?= examples/cornea-campaign-soft-tip.toml
DEMO_MODEL ?= out/cornea-soft.h5
TRAIN_DEMO = $(VENV)/bin/mpirun -n $(NP) $(VENV)/bin/hapticrom train $(DEMO_CAMPAIGN) --out $(DEMO_MODEL)
demo: venv meshes/cornea.msh ## train the demo model (resumed), play, check, report and cut it
	$(TRAIN_DEMO)
	$(VENV)/bin/hapticrom play $(DEMO_MODEL) --out out/play
	$(VENV)/bin/mpirun -n $(NP) $(VENV)/bin/hapticrom accuracy $(DEMO_MODEL) --json out/accuracy.json
	$(VENV)/bin/hapticrom report $(DEMO_MODEL) --out out/report --accuracy out/accuracy.json --held-out $(DEMO_MODEL:.h5=.heldout-8)
	$(PY) bench/cutting_latency.py $(DEMO_MODEL)
	$(PY) bench/cutting_runtime_accuracy.py $(DEMO_MODEL) --out out/cutting-runtime
	@echo "reduced model: $(DEMO_MODEL) (snapshots: $(DEMO_MODEL:.h5=.campaign)); report: out/report/report.html; try: $(VENV)/bin/hapticrom bench $(DEMO_MODEL)"

# The demo model, trained only when it is missing (`make demo` trains it again, resuming).
# Order-only prerequisites: a newer venv or mesh does not make it out of date.
$(DEMO_MODEL): | venv meshes/cornea.msh
	$(TRAIN_DEMO)

bench: $(DEMO_MODEL) | venv meshes/cornea.msh ## full-order, runtime and cutting benchmarks (trains the demo model if missing)
	$(PY) bench/fullorder.py
	$(PY) bench/online.py $(DEMO_MODEL)
	$(PY) bench/cutting_accuracy.py

# The C ABI (include/hapticrom.h, README "Embedding in C, C++, C#, SOFA"): libhapticrom.so
# embeds this venv's CPython (python3.12-config --embed, next to the venv's base interpreter)
# and finds the venv through the path of its python, baked in (HAPTICROM_PYTHON overrides it
# at run time); examples/c/servo_loop.c is a haptic host on it. tests/test_capi.py builds
# both (and the AddressSanitizer build, capi-asan) and runs them.
CAPI_BUILD := build
CAPI_CC ?= gcc
CAPI_CFLAGS ?= -std=c11 -O2 -g -Wall -Wextra -pthread
CAPI_SANITIZE := -fsanitize=address,undefined -fno-omit-frame-pointer
PYTHON_CONFIG = $(shell $(PY) -c 'import os, sys; print(os.path.join(sys.base_prefix, "bin", "python3.12-config"))')
HAPTICROM_VERSION = $(shell sed -n 's/^__version__ = "\(.*\)"/\1/p' src/hapticrom/__init__.py)

capi: $(CAPI_BUILD)/libhapticrom.so $(CAPI_BUILD)/servo_loop ## the C ABI: build/libhapticrom.so and the example host build/servo_loop

capi-asan: $(CAPI_BUILD)/asan/libhapticrom.so $(CAPI_BUILD)/asan/servo_loop ## the same under AddressSanitizer and UBSan, in build/asan

capi-bench: capi $(DEMO_MODEL) $(CAPI_BUILD)/tips.csv ## C ABI latency over 1,000,000 steps of the demo model, contact and position in (p50/p99)
	$(CAPI_BUILD)/servo_loop $(DEMO_MODEL) --bench 1000000 --bench-surfaces 2000
	$(CAPI_BUILD)/servo_loop $(DEMO_MODEL) --tips $(CAPI_BUILD)/tips.csv --bench 1000000 --bench-surfaces 0

# play's scripted path (approach, press at 30 degrees, slide, lift) as tips for servo_loop --tips
$(CAPI_BUILD)/tips.csv: $(DEMO_MODEL) examples/c/scripted_tips.py $(STAMP)
	@mkdir -p $(@D)
	$(PY) examples/c/scripted_tips.py $(DEMO_MODEL) $@ --ticks 3000

$(CAPI_BUILD)/asan/libhapticrom.so $(CAPI_BUILD)/asan/servo_loop: CAPI_EXTRA := $(CAPI_SANITIZE)

$(CAPI_BUILD)/libhapticrom.so $(CAPI_BUILD)/asan/libhapticrom.so: capi/hapticrom.c include/hapticrom.h src/hapticrom/__init__.py $(STAMP)
	@mkdir -p $(@D)
	$(CAPI_CC) $(CAPI_CFLAGS) $(CAPI_EXTRA) -fPIC -shared -Iinclude $$($(PYTHON_CONFIG) --includes) \
	  -DHAPTICROM_DEFAULT_PYTHON='"$(CURDIR)/$(PY)"' -DHAPTICROM_PACKAGE_VERSION='"$(HAPTICROM_VERSION)"' \
	  -o $@ capi/hapticrom.c $$($(PYTHON_CONFIG) --embed --ldflags)

$(CAPI_BUILD)/servo_loop $(CAPI_BUILD)/asan/servo_loop: %/servo_loop: examples/c/servo_loop.c include/hapticrom.h %/libhapticrom.so
	$(CAPI_CC) $(CAPI_CFLAGS) $(CAPI_EXTRA) -Iinclude -o $@ $< -L$(@D) -lhapticrom -Wl,-rpath,'$$ORIGIN' -lm

# Static checks, seconds (part of `make test`): ruff lint and format, and hadolint on the
# Dockerfiles (no Docker engine needed; rules in .hadolint.yaml).
lint: venv ## ruff lint and format check, hadolint on the Dockerfiles
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/hadolint --no-color --config .hadolint.yaml docker/Dockerfile.offline docker/Dockerfile.runtime

clean: ## remove out/ (models, reports) and the pytest cache
	rm -rf out .pytest_cache

# Both Docker images built with buildah and run (docker/test.sh): the runtime plays and
# benches a model without the finite-element stack, the trainer solves and trains the coarse
# cornea under mpirun -n 2. Root, buildah and debootstrap; no Docker engine or registry (a
# local base image, kept). 8 to 15 min; not part of `make test`.
docker-test: ## build and run both Docker images with buildah (root; 8-15 min)
	docker/test.sh
