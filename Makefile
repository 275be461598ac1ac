# Every target sets itself up: on a fresh machine `make demo` and `make test` need nothing else.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: setup test demo bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	$(BIN)/python -m experiments.robots generate --out runs/demo_robots --num 8 --seed 0
	$(BIN)/python -m experiments.robots info runs/demo_robots

bench: $(STAMP)
	$(BIN)/python -m experiments.bench_robots

clean:
	rm -rf $(VENV) .pytest_cache
