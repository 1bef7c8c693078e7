# The two set-up commands of the README: `make demo` and `make test`.
# Each creates the virtualenv (.venv) when it is missing or older than the project files.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.bopsurg-installed
DEMO_OUT ?= demo_out
# pytest worker processes (pytest-xdist): every core; TEST_WORKERS=0 runs in one process
TEST_WORKERS ?= auto

# The core on the other supported Pythons (the whole suite runs on $(PYTHON)).
CORE_PYTHONS ?= python3.10 python3.12 python3.13
# The core tests: they need only the core and bopsurg[test]; the rest of tests/ needs the extras.
CORE_TESTS := tests/bopsurg tests/test_packaging.py

.PHONY: demo test test-after-ray test-pythons wheel lint bench docs venv clean

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

# The wheel users install, in dist/ (built from the checkout, no network).
wheel: $(STAMP)
	rm -rf dist build
	$(BIN)/python -m pip wheel -q --no-deps --no-build-isolation -w dist .

# The wheel installed with the core tests' extra only (no torch, pybullet, rosbags, rerun) into
# a fresh virtualenv of each of CORE_PYTHONS, and the core tests run against it from a copy of
# tests/ outside the checkout, so the installed wheel is imported, not the source tree.
test-pythons: wheel
	set -e; whl=$$(ls dist/bopsurg-*.whl); tmp=$$(mktemp -d); trap 'rm -rf "$$tmp"' EXIT; \
	cp -r tests pyproject.toml "$$tmp/"; \
	for py in $(CORE_PYTHONS); do \
		echo "== core tests on $$py"; t0=$$(date +%s); \
		$$py -c "" || { echo "$$py not found: set CORE_PYTHONS to interpreters"; exit 1; }; \
		$$py -m venv "$$tmp/venv-$$py"; \
		"$$tmp/venv-$$py/bin/python" -m pip install -q -c constraints.txt "$$whl[test]"; \
		t1=$$(date +%s); \
		(cd "$$tmp" && "$$tmp/venv-$$py/bin/python" -m pytest -q -p no:cacheprovider \
			-n $(TEST_WORKERS) $(CORE_TESTS)); \
		echo "== $$py: install $$((t1 - t0)) s, tests $$(($$(date +%s) - t1)) s"; \
	done


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
	rm -rf $(VENV) $(DEMO_OUT) build dist site *.egg-info
