# Two entry points: `make run` (daemon on the simulated robot) and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
ARGS   ?=

.PHONY: run test bench venv clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'
	touch $@

venv: $(VENV)/.installed

run: venv
	$(BIN)/mmctl run $(ARGS)

# --max-worker-restart: a worker that dies (a crash in a C extension, or the
# conftest's hard timeout) fails the run instead of leaving xdist's loadfile
# scheduler waiting forever (seen: a crashed worker hung the whole run).
test: venv
	$(BIN)/python -m pytest -n 2 --dist loadfile --max-worker-restart=2 $(ARGS)

clean:
	rm -rf $(VENV) build src/*.egg-info
