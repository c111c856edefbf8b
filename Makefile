# Two commands do everything on a fresh clone:  make run   /   make test
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.carvi-installed
OUT    ?= outputs/default
# pytest processes for make test, a test file each (most tests wait on a child process or use one thread)
TEST_WORKERS ?= 2

.PHONY: install run test lint clean

# The install is a file target: it re-runs only when pyproject.toml changes.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check torch==2.13.0
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(PY) -m carvi_torch.reconstruct --out $(OUT)

lint: install
	$(PY) -m ruff check carvi_torch tests tools

# lint, then the suite (doctests of the package included: pyproject.toml's pytest options) in
# TEST_WORKERS processes (make test TEST_WORKERS=0: all in this one), whole files in collection order
# (the longest first: tests/conftest.py)
test: lint
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

clean:
	rm -rf $(VENV) outputs .pytest_cache
