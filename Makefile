# Two commands on a fresh machine (each creates .venv and installs what it needs):
#   make run    end-to-end job on the default BROAD data
#   make test   the whole test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

run: $(STAMP)
	$(BIN)/python pipelines/main.py

test: $(STAMP)
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) reports build
