# The only set-up there is: `make run` and `make test` build .venv from nothing but Python.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run reproduce test test-all lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch first, pinned: this version is a CPU build on local disk; anything else downloads GBs.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

# make run: the paper's claim on `hard` (V, 3 seeds of each method to 2000 episodes).
run: $(STAMP)
	$(BIN)/imagine reproduce results --preset fast --tasks hard --seeds 0-2 \
		--budgets 250,500,1000,1500,2000
	@echo "Report: results/REPORT.md (tables in results/tables, figures in results/figures)"

# make reproduce: the paper's whole section V (both tasks, 5 seeds, budgets to 6000), as in
# docs/results.md, which it regenerates.
reproduce: $(STAMP)
	$(BIN)/imagine reproduce results-full --preset fast
	$(BIN)/python -m imagine.study.results_page results-full docs/results.md

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/pytest

test-all: $(STAMP)
	$(BIN)/pytest -m ''

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/python benchmarks/env_speed.py
	$(BIN)/python benchmarks/vae_speed.py
	$(BIN)/python benchmarks/population_speed.py
	$(BIN)/python benchmarks/step_cost.py

clean:
	rm -rf $(VENV) results results-full .pytest_cache .ruff_cache
