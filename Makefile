# Two commands: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
STAMP_TEST := $(VENV)/.installed-test
STAMP_BENCH := $(VENV)/.installed-bench
export MPLBACKEND := Agg
export PYVISTA_OFF_SCREEN := true

.PHONY: demo test test-all docs lint typecheck bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(STAMP_TEST): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,docs]"
	$(BIN)/python -m ipykernel install --sys-prefix --name python3 >/dev/null
	touch $(STAMP) $@

$(STAMP_BENCH): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,bench]"
	touch $@

demo: $(STAMP)
	$(BIN)/doe demo --out demo-output

# The suite, then the checks that keep the tree tidy: lint, types of the public API, the docs.
test: $(STAMP_TEST)
	$(BIN)/python -m pytest -m "not slow" -q -n 2 --dist loadfile --durations=15
	$(MAKE) --no-print-directory lint typecheck docs

lint: $(STAMP_TEST)
	$(BIN)/python -m ruff check .

typecheck: $(STAMP_TEST)
	$(BIN)/python -m mypy

# The documentation site, warnings (broken references and links included) as errors.
docs: $(STAMP_TEST)
	$(BIN)/python -m sphinx -b html -W --keep-going -j 2 docs docs/_build/html

test-all: $(STAMP_TEST)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

bench: $(STAMP_BENCH)
	$(BIN)/python -m benchmarks.run --out benchmarks/results

clean:
	rm -rf $(VENV) demo-output .pytest_cache docs/_build docs/api/generated docs/notebooks build/notebooks
