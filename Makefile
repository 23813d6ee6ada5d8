# facegeo: the two commands of the README do all the set-up themselves.
#   make demo   synthesise the embedded default scan and run the main job on it
#   make test   run the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.facegeo-installed
DEMO_SCAN ?= scans/demo

.PHONY: setup demo test test-fast bench clean system-deps

setup: $(STAMP)

system-deps:
	@sh scripts/ensure-system-deps.sh

$(STAMP): pyproject.toml scripts/ensure-system-deps.sh
	@sh scripts/ensure-system-deps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/facegeo demo $(DEMO_SCAN)

# Two workers (this machine's cores), one test file per worker at a time (module fixtures are
# built once); `pytest -q` alone runs the suite in one process.
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

test-fast: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not slow"

bench: $(STAMP)
	$(VENV)/bin/facegeo bench --out bench-out

clean:
	rm -rf $(VENV) bench-out .pytest_cache
