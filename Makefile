# Every target sets itself up: on a fresh machine `make demo` and `make test` need nothing else.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
# pytest-xdist processes for `make test` (1: serial)
WORKERS ?= 2

.PHONY: setup test demo bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

# whole test files go to $(WORKERS) processes (pytest-xdist; serial if it is missing or WORKERS=1)
test: $(STAMP)
	$(BIN)/python -m pytest -q $$([ "$(WORKERS)" -gt 1 ] && $(BIN)/python -c 'import xdist' 2>/dev/null \
	  && echo "-n $(WORKERS) --dist loadfile")

# the main job in miniature on the embedded default (shipped generated robots): train R-MoMo, evaluate it zero-shot
# on unseen robots, write a report (experiments/demo.py; a real configuration when an accelerator is visible)
demo: $(STAMP)
	$(BIN)/python -m experiments.demo

# the benchmarks (meant for a GPU; each prints one JSON line per case): env throughput of the four tasks and the
# cost of self-collision, then end-to-end training throughput of R-MoMo and ModuMorph on flat terrain
bench: $(STAMP)
	$(BIN)/python -m experiments.bench_env 'cases=[{env: ft},{env: incline},{env: csr},{env: obstacle},{env: ft, self_collision: true}]'
	$(BIN)/python -m experiments.bench_train env=ft arch=rmomo
	$(BIN)/python -m experiments.bench_train env=ft arch=modumorph

clean:
	rm -rf $(VENV) .pytest_cache
