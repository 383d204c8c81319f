# anfekf-bench: every target sets up its own virtual environment first.
VENV   ?= .venv
PYTHON ?= python3
PY     := $(VENV)/bin/python
ANFEKF := $(VENV)/bin/anfekf
OUT    ?= results

.PHONY: setup reproduce run report test lint format bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev,dask]"
	touch $@

## The paper's four experiments at 50 runs each, then the report.
reproduce: run report

run: setup
	$(ANFEKF) run configs/ --out $(OUT) --force

report: setup
	$(ANFEKF) report $(OUT) --out $(OUT)/report

test: setup
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

bench: setup
	$(ANFEKF) bench --out $(OUT)/bench.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
