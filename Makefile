# Two entry points for a fresh machine (see README):
#   make demo   -- create .venv, install, run the feeding task (make demo CAMERA=0: a real camera)
#   make test   -- create .venv, install, run the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-dev

.PHONY: demo test lint bench results venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/psm up $(if $(CAMERA),--camera $(CAMERA))

test: $(STAMP)
	$(VENV)/bin/ruff check psm services tests benchmarks scripts experiments
	$(PY) -m pytest -q -p no:cacheprovider

bench: $(STAMP)
	$(PY) -m benchmarks.learner
	$(PY) -m benchmarks.bus
	$(PY) -m benchmarks.arm
	$(PY) -m benchmarks.goal_tracker
	$(PY) -m benchmarks.stack
	$(PY) -m benchmarks.peers
	$(PY) -m benchmarks.planner
	$(PY) -m benchmarks.feeding
	$(PY) -m benchmarks.obstacles
	$(PY) -m benchmarks.monitor
	$(PY) -m benchmarks.acl
	$(PY) -m benchmarks.viewer

# The paper's experiments, their report (out/experiments/) and the README's results block.
results: $(STAMP)
	$(VENV)/bin/psm experiments --all --seed 1
	$(PY) scripts/readme_results.py

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
