# The two set-up commands of the README: `make demo` and `make test`.
# Each creates the virtualenv (.venv) when it is missing or older than the project files.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.bopsurg-installed
DEMO_OUT ?= demo_out
# pytest worker processes (pytest-xdist): every core; TEST_WORKERS=0 runs in one process
TEST_WORKERS ?= auto

.PHONY: demo test test-after-ray lint bench docs venv clean

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
	$(BIN)/mypy --strict bopsurg generators models

test: lint
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

# The suite again on the same machine, as a user who tried Ray would run it: with a HOME in
# which Ray left ~/.ray/auth_token (its first local cluster writes one) and right after a
# local Ray instance ran a bopsurg command. Catches tests that depend on what ran before.
test-after-ray: $(STAMP)
	home=$$(mktemp -d) && trap 'rm -rf "$$home"' EXIT && \
	HOME=$$home $(BIN)/ray get-auth-token --generate >/dev/null && \
	test -s $$home/.ray/auth_token && \
	HOME=$$home $(BIN)/bopsurg example --out $$home/ex --scenes 1 --images 3 >/dev/null && \
	HOME=$$home $(BIN)/bopsurg -q eval $$home/ex/needle $$home/ex/bopsurgsim_needle-test.csv \
		--out $$home/ev --no-progress --executor ray >/dev/null && \
	HOME=$$home $(BIN)/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS)

# The README's speed table as Markdown, measured in one run (bench/speed_table.py). Add e.g.
# BENCH_ARGS="--device cuda" or "--data demo_out/data --results demo_out/results.csv
# --toolkit ../bop_toolkit --toolkit-python ../bop-venv/bin/python" (ratio to the reference).
BENCH_ARGS ?=
bench: $(STAMP)
	$(BIN)/python bench/speed_table.py $(BENCH_ARGS)

# The documentation site (docs/, mkdocs.yml) into site/; --strict fails on any warning
# (a broken link, a missing page, a docstring the API reference cannot read).
docs: $(STAMP)
	test -x $(BIN)/mkdocs || $(BIN)/python -m pip install -q -c constraints.txt -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) $(DEMO_OUT) build site *.egg-info
