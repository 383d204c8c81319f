# anfekf-bench: every target sets up its own virtual environment first.
VENV   ?= .venv
PYTHON ?= python3
PY     := $(VENV)/bin/python
ANFEKF := $(VENV)/bin/anfekf
OUT    ?= results

.PHONY: setup reproduce run report test test-quick test-all lint format bench gate clean readme docs zoo sweeps real changing drives bias learned learned-drives default

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev,dask,fast]"
	@# numba compiles on one core: two processes side by side (measured 2026-11-28: 37 + 34 s
	@# beside 73 s), the robot's families' loops and then the problems' loops (SPEC 17) in one,
	@# the robot's other kernels in the other (cache writes locked: fast.serialise_cache_writes).
	$(PY) -m anfekf_bench.engines.fast --warm-up --part kernels & kernels=$$!; \
	    $(PY) -m anfekf_bench.engines.fast --warm-up --part loop \
	    && $(PY) -c "import anfekf_bench.problems.fast"; rest=$$?; \
	    wait $$kernels && exit $$rest
	touch $@

## The paper's four experiments at 50 runs each, then the report (after the runs, even with -j).
reproduce: run
	$(MAKE) report

run: setup
	$(ANFEKF) run configs/ --out $(OUT) --force

report: setup
	$(ANFEKF) report $(OUT) --out $(OUT)/report

## The tests run on up to 4 processes (pytest-xdist; 2 on the 2-core CI machine). `make test` is
## what CI runs: every test but the few marked `heavy`; `make test-quick` leaves out the `slow`
## end-to-end tests too (about a minute); `make test-all` runs everything.
PYTEST := $(PY) -m pytest -q -n auto --maxprocesses 4 --dist worksteal
test: setup
	$(PYTEST) -m "not heavy" --durations=25

test-quick: setup
	$(PYTEST) -m "not slow"

test-all: setup
	$(PYTEST)

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports

format: setup
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

## The generated parts of the README and the docs (scenario keys, filter kinds, the command line,
## the bench figures, docs/*.schema.json), from the models, the commands and results/bench.json.
readme: setup
	$(PY) -m anfekf_bench.docgen

## The documentation site (mkdocs.yml, docs/) into site/; any warning (a broken link or anchor
## included) fails the build. Needs the docs extra: pip install -e ".[docs]".
docs: setup
	@$(PY) -c "import mkdocs, material, mkdocstrings_handlers.python" 2>/dev/null || { echo "make docs needs the docs extra: $(VENV)/bin/pip install -e '.[docs]'"; exit 2; }
	$(PY) -m anfekf_bench.docgen --check
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

bench: setup
	$(ANFEKF) bench --out $(OUT)/bench.json

## Regression gate (docs/how-to/regression-gate.md): the four scenarios at 20 runs against the committed baseline.
## Refresh the baseline on purpose with: make gate GATE_FLAGS=--update
GATE_OUT      ?= $(OUT)/ci-gate
GATE_BASELINE ?= results/baselines/ci.json
GATE_FLAGS    ?=
gate: setup
	$(ANFEKF) run configs/ci --out $(GATE_OUT) --force
	$(ANFEKF) check $(GATE_OUT) --baseline $(GATE_BASELINE) $(GATE_FLAGS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache anfekf_bench/engines/__pycache__/loops

## Beyond the paper (docs/results/): the adaptive-filter zoo, the mismatch sweeps, the real robot log.
zoo: setup
	$(ANFEKF) run configs/zoo --out $(OUT)/zoo --force
	$(ANFEKF) report $(OUT)/zoo --out $(OUT)/zoo/report

sweeps: setup
	$(ANFEKF) run configs/sweeps --out $(OUT)/sweeps --force
	$(ANFEKF) report $(OUT)/sweeps --out $(OUT)/sweeps/report

changing: setup
	$(ANFEKF) run configs/changing --out $(OUT)/changing --force
	$(ANFEKF) report $(OUT)/changing --out $(OUT)/changing/report

## The worst case over zoo + changing (SPEC 19, docs/results/default-filter.md): one report over
## both suites, its worst-case table (worst_case.csv) ranking every filter by its worst ratio.
default: setup
	$(ANFEKF) run configs/zoo --out $(OUT)/zoo --skip-existing
	$(ANFEKF) run configs/changing --out $(OUT)/changing --skip-existing
	$(ANFEKF) report $(OUT)/zoo $(OUT)/changing --out $(OUT)/default/report

real: setup
	$(ANFEKF) run configs/real --out $(OUT)/real --force
	$(ANFEKF) report $(OUT)/real --out $(OUT)/real/report

drives: setup
	$(ANFEKF) run configs/drives --out $(OUT)/drives --force
	$(ANFEKF) report $(OUT)/drives --out $(OUT)/drives/report

## Errors that are not white noise (SPEC 18, docs/results/bias.md): a simulated scenario per error
## source (configs/bias) and the augmented EKF on the eleven drives (configs/bias-drives).
bias: setup
	$(ANFEKF) run configs/bias --out $(OUT)/bias --force
	$(ANFEKF) run configs/bias-drives --out $(OUT)/bias --force
	$(ANFEKF) report $(OUT)/bias --out $(OUT)/bias/report
	$(PY) examples/bias/estimates.py
	$(PY) examples/bias/estimates.py --filter ekf-aug-calibrated
	$(PY) examples/bias/drives.py $(OUT)/bias/mrclam-drives-aug

## KalmanNet (docs/DESIGN.md): configs/learned, the four paper scenarios and the zoo's two mirrors
## with ekf, anfekf, ekf-oracle and kalmannet; `anfekf run` trains KalmanNet on 50 training runs
## (seeds disjoint from the 20 scored) and compares it with the others, paired over runs.
## Needs the extra, PyTorch's CPU build first (else pip pulls the 3.2 GB CUDA build on Linux):
##   pip install torch --index-url https://download.pytorch.org/whl/cpu && pip install -e ".[learned]"
learned: setup
	@$(PY) -c "import torch" 2>/dev/null || { echo "make learned needs PyTorch (the CPU build is enough):"; echo "  $(VENV)/bin/pip install torch --index-url https://download.pytorch.org/whl/cpu"; echo "  $(VENV)/bin/pip install -e '.[learned]'"; exit 2; }
	$(ANFEKF) run configs/learned --out $(OUT)/learned --force
	$(ANFEKF) report $(OUT)/learned --out $(OUT)/learned/report

## KalmanNet on the eleven MRCLAM drives (configs/learned-drives): trained per cross-drive fold on
## that fold's training drives (Dataset 6 scores 7, 7 scores 6, both score 9), against ekf-tuned.
learned-drives: setup
	@$(PY) -c "import torch" 2>/dev/null || { echo "make learned-drives needs PyTorch (the CPU build is enough):"; echo "  $(VENV)/bin/pip install torch --index-url https://download.pytorch.org/whl/cpu"; echo "  $(VENV)/bin/pip install -e '.[learned]'"; exit 2; }
	$(ANFEKF) run configs/learned-drives --out $(OUT)/learned-drives --force
	$(ANFEKF) report $(OUT)/learned-drives --out $(OUT)/learned-drives/report
