# panogs developer commands. `make help` lists them.
VENV ?= .venv
PY := $(VENV)/bin/python
PANOGS := $(VENV)/bin/panogs
# torch is pinned to 2.13.0. Where PyPI would hand you the CUDA build, add the CPU index (its 2.13.0+cpu ranks
# above PyPI's 2.13.0, and torch's own dependencies still come from PyPI under the constraints):
#   make install TORCH_INDEX="--extra-index-url https://download.pytorch.org/whl/cpu"
TORCH_INDEX ?=
# Every install takes the versions the tests ran with (constraints.txt, written by `make constraints`).
PIP_INSTALL := $(PY) -m pip install -q -c constraints.txt
DEMO ?= demo
export HF_HUB_OFFLINE ?= 1
export TOKENIZERS_PARALLELISM ?= false

.PHONY: help system-deps install constraints demo readme readme-check test test-fast lint fmt bench bench-quality \
	bench-speed bench-gaussians clean web web-check view bench-viewer deploy-check migrations-check docs-tables docs-cli

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-14s %s\n", $$1, $$2}'

system-deps: ## check Python and the system libraries first (as root: apt-get installs what is missing)
	@tools/check-system-deps

$(VENV)/.installed: pyproject.toml constraints.txt | system-deps
	python3 -m venv $(VENV)
	$(PIP_INSTALL) torch==2.13.0 $(TORCH_INDEX)
	$(PIP_INSTALL) -e '.[pipeline,text,service,worker,dev]'
	touch $@

install: system-deps $(VENV)/.installed web ## create .venv and install panogs with every extra (and build the app)

# The web app (viewer + app): npm ci from the committed lock file, esbuild into service/static/app (git-ignored),
# which FastAPI serves and the wheel carries. Rebuilt when a source under web/ changes.
WEB_BUILT := service/static/app/index.html
WEB_SOURCES := web/package.json web/package-lock.json web/build.mjs \
	$(wildcard web/src/*.js web/src/*/*.js web/src/*/*/*.js web/public/*)

# node and npm are checked (and installed as root) only here: once the build exists and is newer than its sources,
# the Python targets (lint, test, demo) need no node.
$(WEB_BUILT): $(WEB_SOURCES)
	@tools/check-system-deps --web
	cd web && npm ci --no-audit --no-fund --loglevel=error && npm run build

web: $(WEB_BUILT) ## build the web app into service/static/app

# ESLint and Prettier (web/eslint.config.js, web/.prettierrc), then node --test on the pure modules (web/test).
# npm ci only when web/node_modules is missing.
web-check: ## lint (ESLint, Prettier) and unit-test (node --test) the web code
	cd web && { test -d node_modules || npm ci --no-audit --no-fund --loglevel=error; } && npm run lint && npm test

view: install ## open the viewer on the demo's result (after make demo)
	$(PANOGS) view $(DEMO)/run --open

constraints: ## after changing a dependency: install it, then pin the whole closure in constraints.txt
	$(PY) -m pip install -q -e '.[pipeline,text,service,worker,dev]'
	$(PY) tools/freeze_constraints.py > constraints.txt

demo: install ## synthetic room -> whole pipeline -> instance table -> text query -> a rendered view
	$(PANOGS) synth $(DEMO)/scene --preset small --difficulty default --seed 0
	$(PANOGS) run $(DEMO)/scene --out $(DEMO)/run
	$(PANOGS) query $(DEMO)/run chair
	$(PANOGS) render $(DEMO)/run --frame 000000 --out $(DEMO)/render

readme: install docs-tables ## run the demo afresh and write its output into README.md (between the demo-output markers)
	$(PY) tools/readme_demo.py

readme-check: install ## run the demo afresh and fail when README.md shows other results (or other run-folder tables)
	$(PY) tools/run_folder_docs.py --check
	$(PY) tools/readme_demo.py --check

docs-tables: $(VENV)/.installed ## write the generated docs: run-folder tables, docs/settings.md, the module lists, the layer sketch
	$(PY) tools/run_folder_docs.py --write
	$(PY) tools/reference_docs.py --write
	$(PY) tools/layer_sketch.py --write

docs-cli: $(VENV)/.installed ## write docs/cli.md, the reference of every command, from the parsers
	$(PY) tools/cli_docs.py --write

# The suite runs in PYTEST_WORKERS processes (pytest-xdist; each test file whole in one of them, so that a module's
# shared fixtures are made once); PYTEST_WORKERS=0 runs it in this process. The service tests make their own
# databases, Redis key prefixes and ports (random names, free ports: tests/support/service_harness.py), so two
# processes do not see each other's.
PYTEST_WORKERS ?= 2
PYTEST_PARALLEL := $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist loadfile)

test: $(VENV)/.installed $(WEB_BUILT) ## the whole test suite (needs PostgreSQL and Redis on 127.0.0.1; under CI=true they must answer)
	$(VENV)/bin/pytest -q $(PYTEST_PARALLEL)

test-fast: $(VENV)/.installed $(WEB_BUILT) ## the whole tree but the tests marked slow (about a minute; PostgreSQL and Redis as for test)
	$(VENV)/bin/pytest -q -m "not slow" $(PYTEST_PARALLEL)

lint: $(VENV)/.installed ## ruff (lint + format check) over every Python folder, mypy (strict on service and worker)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# The migrations upgraded to head, checked against the models, downgraded to base and upgraded again, on SQLite and
# PostgreSQL (tests/migrations; also part of `make test`).
migrations-check: $(VENV)/.installed ## the migration round trip on both databases
	$(VENV)/bin/pytest -q tests/migrations

fmt: $(VENV)/.installed ## format the code
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: bench-quality bench-speed bench-gaussians ## every benchmark

bench-quality: install ## quality table: difficulties x seeds, full method and ablations
	$(PY) bench/quality.py

bench-speed: install ## per-stage time and peak RSS on the large preset, with the I/O floor
	$(PY) bench/speed.py

bench-viewer: install ## viewer load time to interactive in headless Chromium, 100k and 1M primitives
	$(PY) bench/viewer_load.py

bench-gaussians: install ## Gaussian scene: held-out PSNR/SSIM of the fit, CPU cost per iteration and per render
	$(PY) bench/gaussians.py quality
	$(PY) bench/gaussians.py cost
	$(PY) bench/gaussians.py stage

# The docker deployment built and run end to end (tools/deploy-check): both images (stand-in bases made from Debian
# packages when no registry answers), the compose stack with two workers, the README's curl session, a worker
# stopped mid-job, then the teardown of what it started. Needs Docker with Compose v2, curl, jq and zip; no .venv.
deploy-check: ## build the images, run the compose stack end to end, tear it down
	tools/deploy-check

clean: ## remove demo output and caches
	rm -rf $(DEMO) .pytest_cache .ruff_cache .mypy_cache tests/web/artifacts
