# Two commands do everything on a fresh clone:  make run   /   make test
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.carvi-installed
OUT    ?= outputs/default

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

# lint, then the suite (doctests of the package included: pyproject.toml's pytest options)
test: lint
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) outputs .pytest_cache
