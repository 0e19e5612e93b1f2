# deep-ssfr: `make demo` runs the whole job on the small default; `make test` runs the tests.
# Stage targets take CONFIG=configs/<file>.yaml SCENE=<name> FORCE=1 VERIFY=1.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
CLI := $(VENV)/bin/deep-ssfr
CONFIG ?= configs/default.yaml
SCENE ?=
FORCE ?=
VERIFY ?=
FORMAT ?= ply
STAGE_ARGS = --config $(CONFIG) $(if $(SCENE),--scene $(SCENE)) $(if $(FORCE),--force) $(if $(VERIFY),--verify)
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri
export PYOPENGL_PLATFORM ?= egl

.PHONY: setup test test-fast lint demo simulate dataset train train-ddp ship render evaluate metaball-dataset metaball-train \
	metaball-ship export bench cache-ls clean-cache

setup: $(VENV)/.installed

# Debian packages for headless GL (pyrender over EGL), installed when root and missing.
$(VENV)/.apt-checked:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then echo "installing$$missing"; apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else echo "warning: missing Debian packages$$missing (needed for pyrender); install them as root"; fi; \
	fi
	@test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	@touch $@

# torch first: the CPU build on this machine (a GPU user installs their own torch beforehand).
$(VENV)/.installed: pyproject.toml $(VENV)/.apt-checked
	@$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	@touch $@

# two workers, a test file each at a time: a module's cluster and hosts stay in one process, and the
# many tests that wait on timeouts and other processes overlap the ones that compute
PYTEST := $(PY) -m pytest -q -n 2 --dist loadfile

test: setup
	$(PYTEST)

# the inner loop: every test but the end-to-end stage runs and multi-process fault tests
test-fast: setup
	$(PYTEST) -m "not slow"

lint: setup
	$(VENV)/bin/ruff check .

# every stage is a command of the deep-ssfr console script (deep-ssfr --help)
simulate dataset train ship render evaluate demo metaball-dataset metaball-train: setup
	$(CLI) $@ $(STAGE_ARGS)

metaball-ship: setup
	$(CLI) metaball-ship --config $(CONFIG) $(if $(FORCE),--force) $(if $(VERIFY),--verify)

export: setup
	$(CLI) export $(STAGE_ARGS) --format $(FORMAT)

# `make train` over NPROC data-parallel processes (gloo on the CPU, nccl with one GPU each); several
# nodes: TORCHRUN_ARGS="--nnodes 2 --rdzv-backend c10d --rdzv-endpoint HOST:29400 --rdzv-id RUN"
# on every node (docs/training_at_scale.md)
NPROC ?= 2
TORCHRUN_ARGS ?= --standalone
train-ddp: setup
	$(VENV)/bin/torchrun $(TORCHRUN_ARGS) --nproc_per_node $(NPROC) -m stages.cli train $(STAGE_ARGS)

bench: setup
	$(PY) -m pip install -q -e '.[dev,bench]'
	$(PY) benchmarks/bench_sim.py --peers
	$(PY) benchmarks/bench_dataset.py
	$(PY) benchmarks/bench_train.py
	$(PY) benchmarks/bench_render.py --demo

cache-ls: setup
	$(CLI) cache ls --config $(CONFIG)

clean-cache: setup
	$(CLI) cache clean --config $(CONFIG)
