# Two commands: `make train` (set up + main job) and `make test` (set up + test suite).
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed-stamp

.PHONY: train test scenarios clean

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet -e '.[dev]'
	touch $(STAMP)

# Main job: train the default attacker (attacker_v14); ARGS passes Hydra overrides.
train: $(STAMP)
	$(VENV)/bin/python train.py $(ARGS)

# The default scenario set and its quality report.
scenarios: $(STAMP)
	$(VENV)/bin/python -m rlplat.scenarios out_dir=data/scenarios/pursuit

# The suite spread over one worker per core (pytest-xdist): each worker starts on a contiguous
# share of the tests (a test file's module-scoped fixtures built once) and an idle one takes
# tests from the others' ends, so the long learning tests do not finish alone.
test: $(STAMP)
	$(VENV)/bin/python -m pytest -n auto --dist worksteal

clean:
	rm -rf $(VENV) data .pytest_cache .ruff_cache
