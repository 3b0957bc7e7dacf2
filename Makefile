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

# The main job on the embedded default: the default synthetic city (generated once), then a LeCO run on it with
# the cpu profile on two local Ray workers. An unfinished run resumes; a finished one is shown again.
SCENE := scenes/city-0
RUN   := runs/city-0-leco
run: $(STAMP)
	test -d $(SCENE) || $(BIN)/leco scene synth --preset city --seed 0 --out $(SCENE)
	test -f $(RUN)/summary.json || $(BIN)/leco train --scene $(SCENE) --method leco --profile cpu --workers 2 --out $(RUN)
	@echo "run folder: $(RUN) (summary.json, metrics.jsonl, renders/, occupancy.ply)"

test: $(STAMP)
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) scenes runs .pytest_cache
