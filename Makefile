# Two commands do all set-up on a fresh machine (see README):
#   make run    create .venv, install the package, run the main job (python train.py)
#   make test   create .venv, install the package and test tools, run the whole test suite
#               (which builds the docs site and runs the docs' examples)
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# EGL renders headless (GPU driver or Mesa's software renderer); see README for OSMesa.
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= $(MUJOCO_GL)

.PHONY: run demo report bench test test-long docs docs-long install clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch first, pinned to a CPU build, so the train extra's "torch>=2.3" pulls no CUDA packages.
# On a CUDA machine: make TORCH_SPEC="torch --index-url https://download.pytorch.org/whl/cu126"
TORCH_SPEC ?= torch==2.13.0

# Reinstalled whenever pyproject.toml changes.
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet $(TORCH_SPEC)
	$(BIN)/python -m pip install --quiet -e ".[dev,train,docs,sweep]"
	touch $@

# Every compiled kernel into numba's disk cache (about a minute), and again when one changes;
# otherwise the first run in a checkout, and each of its test workers, compiles them.
$(VENV)/.kernels: $(VENV)/.installed $(wildcard liuxing_envs/kernels/*.py)
	$(BIN)/python -m liuxing_envs.kernels
	touch $@

install: $(VENV)/.kernels

# The default run: PPO on ViewPlanning-v1, then its held-out score against the four-view baseline.
run: $(VENV)/.kernels
	$(BIN)/python train.py

# The committed evaluation report (reports/shipped/report.md): the shipped policies and the
# reference baselines of both environments, 100 held-out episodes each.
SHIPPED_POLICIES := $(patsubst %/config.yml,%,$(sort $(wildcard policies/*/*/config.yml)))
report: $(VENV)/.kernels
	$(BIN)/python evaluate.py $(SHIPPED_POLICIES) --env InstrumentGrasp-v1 \
		--out reports/shipped --save-reconstructions 1 --video

# benchmarks/RESULTS.md: throughput, time split, physics limit, FetchPickAndPlace-v4 side by
# side, vector scaling and training throughput (about 25 minutes; run on a quiet machine).
bench: $(VENV)/.kernels
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python -m benchmarks

demo: $(VENV)/.kernels
	$(BIN)/python -m liuxing_envs.demo --out outputs/demo

# One test process per core (pytest-xdist); TEST_WORKERS=0 runs them all in this process.
TEST_WORKERS ?= auto
test: $(VENV)/.kernels
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal -m "not cluster and not long"

# What is too slow for make test, run by CI after it: the whole pipelines (the built wheel in
# a venv of its own scoring the shipped policies, benchmark and soak runs), then the real Ray
# sweeps (each starts Ray on every core, so one at a time): the smoke sweep, a two-node
# cluster whose trial worker is killed, an interrupted sweep, an Optuna search.
test-long: $(VENV)/.kernels
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal -m long
	$(BIN)/python -m pytest -m cluster

# The docs site on http://127.0.0.1:8000 (python -m docgen first makes its generated pages).
docs: $(VENV)/.installed
	$(BIN)/python -m docgen
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs serve

# Every example of the README and the docs, the long ones too (trainings, reports, benchmarks).
docs-long: $(VENV)/.kernels
	LIUXING_RUN_LONG_EXAMPLES=1 $(BIN)/python -m pytest tests/test_docs.py -k every_example

clean:
	rm -rf $(VENV) outputs site .pytest_cache
