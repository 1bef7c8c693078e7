# The two set-up commands of the README: `make demo` and `make test`.
# Each creates the virtualenv (.venv) when it is missing or older than the project files.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.bopsurg-installed
DEMO_OUT ?= demo_out

.PHONY: demo test lint bench venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[all,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/bopsurg demo --out $(DEMO_OUT)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check bopsurg generators models tests bench
	$(BIN)/lint-imports --no-cache
	$(BIN)/mypy --strict bopsurg

test: lint
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python bench/bench_metrics.py
	$(BIN)/python bench/bench_eval.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
