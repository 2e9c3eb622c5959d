# Two commands on a fresh machine (each creates .venv and installs what it needs):
#   make run    end-to-end job on the default BROAD data
#   make test   the whole test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test venv clean

RUN_STAMP := $(VENV)/.installed-run

# $(call install,EXTRA): the venv with the package and one of its extras
define install
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[$(1)]'
endef

# make test: every extra the tests need (dev); it covers make run's too
$(STAMP): pyproject.toml
	$(call install,dev)
	touch $(STAMP) $(RUN_STAMP)

# make run: only what the main job needs (the run extra), so a fresh machine starts it sooner
$(RUN_STAMP): pyproject.toml
	$(call install,run)
	touch $(RUN_STAMP)

venv: $(STAMP)

run: $(RUN_STAMP)
	$(BIN)/python pipelines/main.py

test: $(STAMP)
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) reports build
