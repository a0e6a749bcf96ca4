# Two entry points: `make run` (daemon on the simulated robot) and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
ARGS   ?=

.PHONY: run test bench venv venv-run clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# `make run`: the package alone (the daemon, its transports, the simulated robot and
# the terminal's live view); the extras (rerun, the study's figures, ROS 2) on demand
$(VENV)/.installed-run: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

# `make test`: everything the tests use (a superset of the above)
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed-run

venv-run: $(VENV)/.installed-run

venv: $(VENV)/.installed

run: venv-run
	$(BIN)/mmctl run $(ARGS)

# --max-worker-restart=0: a worker that dies (a crash in a C extension, or the
# conftest's hard timeout) ends the run at once with "worker crashed while running
# <test>"; with restarts, xdist's loadfile scheduler was seen waiting forever after a
# crash (the CI run that went over its time).
test: venv
	$(BIN)/python -m pytest -n 2 --dist loadfile --max-worker-restart=0 $(ARGS)

clean:
	rm -rf $(VENV) build src/*.egg-info
