# safemimic: the commands a newcomer types. Each creates .venv itself and installs what it needs.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: help install test bench reliability demo figures clean

help:
	@echo "make demo     run the stack end to end on this machine and print what happens"
	@echo "make test     run the whole test suite (real Zenoh, MuJoCo, Pinocchio, QP solvers)"
	@echo "make bench    run the benchmarks, print a table, write JSON under bench/results/ and docs/benchmarks.md"
	@echo "make reliability  watchdogs, rate limits, kill -9 faults, fuzzed input, load: bench/results/reliability.json"
	@echo "make figures  evaluate the paper's two scenarios with and without the CBF: README figures in docs/figures/"

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m safemimic.cli pose-model install
	touch $(STAMP)

install: $(STAMP)

# The layers first (import-linter contracts in pyproject.toml: shared <- services <- safemimic), then
# the tests. pytest exit 5 means "no tests collected": that is a failure here, never a silent pass.
test: $(STAMP)
	@$(VENV)/bin/lint-imports
	@$(PY) -m pytest -q; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests" >&2; exit 1; fi; exit $$rc

# The point filter's lag is measured on the team's development clips (beside the checkout).
SAFEMIMIC_MOCAP_DIR ?= $(abspath ../shared/data/mocap)
bench: $(STAMP)
	SAFEMIMIC_MOCAP_DIR=$(SAFEMIMIC_MOCAP_DIR) $(PY) -m bench.run --docs docs/benchmarks.md

# The long variant of every reliability check (tests/reliability, one test per check; under 10 minutes),
# every timing budget held, and the report; the quick variant of every check runs in make test.
reliability: $(STAMP)
	@$(PY) -m pytest -q tests/reliability --reliability-long --reliability-report bench/results/reliability.json; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make reliability: pytest collected no tests" >&2; exit 1; fi; exit $$rc

# The paper's two scenarios (Figs. 2-3), each run with and without the CBF layer: metrics.json,
# joints.png, barriers.png and snapshot.png per scenario in docs/figures/ (shown in README.md).
FIGURE_SCENARIOS := cross-arm-reach side-by-side-arm-raise
figures: $(STAMP)
	@for scenario in $(FIGURE_SCENARIOS); do \
		$(PY) -m safemimic.cli evaluate --scenario $$scenario --placement side-by-side --out docs/figures/$$scenario || exit 1; \
	done

demo: $(STAMP)
	$(PY) -m safemimic.cli demo

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis build *.egg-info bench/results/*.json
