# Set-up lives here: `make test` and `make demo` build .venv on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out
RESULTS_SCENARIOS ?= 1000
RESULTS_FLAGS ?= --paper

.PHONY: test demo bench results clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n auto tests

demo: $(STAMP)
	$(BIN)/vitreoguard demo --out $(OUT)/demo

bench: $(STAMP)
	$(BIN)/python -m bench

# every tool's JSON under $(OUT)/results, then the tables in docs/results.md
results: $(STAMP)
	$(BIN)/python -m eval.experiments.results_report --out $(OUT)/results --scenarios $(RESULTS_SCENARIOS) $(RESULTS_FLAGS)

clean:
	rm -rf $(VENV) $(OUT)
