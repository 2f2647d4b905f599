# panogs developer commands. `make help` lists them.
VENV ?= .venv
PY := $(VENV)/bin/python
PANOGS := $(VENV)/bin/panogs
# torch is pinned to the CPU build 2.13.0. Where PyPI would hand you the CUDA build, point pip at the CPU index:
#   make install TORCH_INDEX="--index-url https://download.pytorch.org/whl/cpu"
TORCH_INDEX ?=
DEMO ?= demo
export HF_HUB_OFFLINE ?= 1
export TOKENIZERS_PARALLELISM ?= false

.PHONY: help install demo test test-fast lint fmt bench bench-quality bench-speed clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-14s %s\n", $$1, $$2}'

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0 $(TORCH_INDEX)
	$(PY) -m pip install -q -e '.[text,service,worker,dev]'
	touch $@

install: $(VENV)/.installed ## create .venv and install panogs with every extra

demo: install ## synthetic room -> whole pipeline -> instance table -> text query
	$(PANOGS) synth $(DEMO)/scene --preset small --difficulty default --seed 0
	$(PANOGS) run $(DEMO)/scene --out $(DEMO)/run
	$(PANOGS) query $(DEMO)/run chair

test: install ## the whole test suite (needs PostgreSQL and Redis on 127.0.0.1)
	$(VENV)/bin/pytest -q

test-fast: install ## core tests only
	$(VENV)/bin/pytest -q tests/core

lint: install ## ruff (lint + format check) and mypy on panogs_core
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check panogs_core
	$(VENV)/bin/mypy

fmt: install ## format the code
	$(VENV)/bin/ruff format panogs_core service worker tests bench
	$(VENV)/bin/ruff check --fix .

bench: bench-quality bench-speed ## every benchmark

bench-quality: install ## quality table: difficulties x seeds, full method and ablations
	$(PY) bench/quality.py

bench-speed: install ## per-stage time and peak RSS on the large preset, with the I/O floor
	$(PY) bench/speed.py

clean: ## remove demo output and caches
	rm -rf $(DEMO) .pytest_cache .ruff_cache .mypy_cache
