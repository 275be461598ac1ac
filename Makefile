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

# the main job on the embedded default: a smoke run of R-MoMo on flat terrain with the shipped generated robots
demo: $(STAMP)
	$(BIN)/python -m experiments.run preset=smoke env=ft arch=rmomo robots=gen/train run_dir=runs/demo
	@echo "learning curve: runs/demo/learning_curve.png"

bench: $(STAMP)
	$(BIN)/python -m experiments.bench_robots

clean:
	rm -rf $(VENV) .pytest_cache
