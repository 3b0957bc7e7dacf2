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

# The main job on the embedded default: `leco serve` (SQLite + local artifact root + local Ray, migrated for
# the user), then `leco submit` registers the default synthetic city, submits a LeCO job (cpu profile, two
# Ray workers) and follows it to the end; the service stops afterwards. Data lives in leco-data/.
run: $(STAMP)
	deploy/main-job.sh

# Lint and types first (seconds), then the suite. If a test kills pytest, the last lines printed name it
# and the frames it died in (tests/crash_report.py).
test: $(STAMP)
	$(BIN)/ruff check model workers service bench cli tests
	$(BIN)/ruff format --check model workers service bench cli tests
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 --durations=40 || { status=$$?; $(BIN)/python -m tests.crash_report; exit $$status; }

clean:
	rm -rf $(VENV) scenes runs leco-data .pytest_cache
