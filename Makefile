# Two commands on a fresh machine: `make run` (the main job) and `make test`.
# Both create .venv in the repository and install everything they need.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export RERUN_ANALYTICS := 0
export MUJOCO_GL ?= egl

.PHONY: venv run test bench clean

venv: $(STAMP)

# torch first, pinned: pip then takes the CPU build on this machine's disk
# instead of resolving a multi-GB CUDA build through another package.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# The main job: the distributed system on this machine (router, learner, 2 actors, evaluator),
# 500 learner updates of the `fast` preset on paper-indoor (the paper's "DRL 500" stage), then
# the test protocol and the report. Everything lands in runs/main/.
RUN_ARGS ?= --actors 2 --preset fast --updates 500 --run main --final-episodes 2

run: venv
	$(VENV)/bin/cogexplore up $(RUN_ARGS)

test: venv
	$(VENV)/bin/python -m pytest -q

bench: venv
	$(VENV)/bin/cogexplore bench env --json
	$(VENV)/bin/cogexplore bench learner --json

clean:
	rm -rf $(VENV) runs build *.egg-info
