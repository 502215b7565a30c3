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

# torch first, pinned, the build this machine should run (scripts/install_torch.py: the CPU
# index without an NVIDIA GPU, PyPI's CUDA build with one, the default index when the CPU index
# is unreachable); resolved through the project's pin instead, pip would pull the CUDA build.
$(STAMP): pyproject.toml scripts/install_torch.py
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) scripts/install_torch.py
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# The main job: the distributed system on this machine (router, learner, 2 actors, evaluator)
# training the default preset (shared.config.DEFAULT_PRESET, the shipped model's recipe) on
# paper-indoor for 10.5 minutes, then the test protocol (both protocols) on the mean of the last
# four checkpoints' weights (up --final-average) and the report: about 11 minutes in all on 2
# cores. Everything lands in runs/main/. A second `make run` trains the same run on from its last
# checkpoint for another 10.5 minutes; `--fresh` starts over (the old run kept aside
# as runs/main.old-<time>): `.venv/bin/cogexplore up --run main --fresh --minutes 10.5`.
RUN_ARGS ?= --actors 2 --minutes 10.5 --run main --final-episodes 2

run: venv
	$(VENV)/bin/cogexplore up $(RUN_ARGS)

test: venv
	$(VENV)/bin/python -m pytest -q

bench: venv
	$(VENV)/bin/cogexplore bench env --json
	$(VENV)/bin/cogexplore bench learner --json

clean:
	rm -rf $(VENV) runs build *.egg-info
