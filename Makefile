# Two entry points for a fresh machine (see README): `make run` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install run test clean

install: $(STAMP)

# Re-install whenever the dependency list changes; torch==2.13.0 resolves to the local CPU wheel.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

# The main job on the embedded default: for now, generate the default synthetic city and describe it.
run: $(STAMP)
	$(BIN)/leco scene synth --preset city --seed 0 --out scenes/city-0
	$(BIN)/leco scene info scenes/city-0

test: $(STAMP)
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) scenes .pytest_cache
