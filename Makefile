# kftrack course-book. Quick start: `make book` builds the site, `make test` runs every test.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# Deterministic numerics in notebooks and tests (kernels inherit this environment).
# MPLBACKEND is deliberately not set: it would drop the figures from executed notebooks.
RUN    := PYTHONHASHSEED=0 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
NBVAL  := --nbval --nbval-current-env --nbval-sanitize-with tests/nbval_sanitize.cfg
# Both cores (pytest-xdist): whole files go to a worker, so a notebook's cells run in order in one kernel.
JOBS   ?= 2
XDIST  := -n $(JOBS) --dist loadfile

.PHONY: help venv book test unit nbval booktest lab execute clean portability benchmark lite-check

help:
	@echo "make book     build the site into _build/html from the executed notebooks (+ _build/html/lite: run in the browser)"
	@echo "make test     unit tests, nbval over notebooks/, then the book build (-W)"
	@echo "make lab      JupyterLab on notebooks/"
	@echo "make execute  re-execute every notebook in place (NB=notebooks/02-*.ipynb for one)"
	@echo "make portability  unit tests + nbval under several OpenBLAS/NumPy SIMD kernels (UNIT_ONLY=1)"
	@echo "make lite-check  every chapter run in JupyterLite in headless Chromium, time per chapter (2–4 min each on 2 shared cores)"
	@echo "make clean    remove _build/ and caches (keeps .venv)"
	@echo "make benchmark  kftrack vs peers (installs benchmarks/requirements.txt; ~5 min; writes book/performance_results.md)"

# (Re)create the virtual environment when it is missing or older than the requirements.
# The site's JavaScript (require.js, the widget manager) comes pinned from npm: book/_js.
$(STAMP): requirements.txt constraints.txt pyproject.toml book/_js/package-lock.json
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -r requirements.txt
	cd book/_js && npm ci --no-audit --no-fund --ignore-scripts --loglevel=error
	touch $(STAMP)

venv: $(STAMP)

book: $(STAMP)
	$(RUN) $(BIN)/jupyter-book build . -W -n --keep-going
	@echo "Open $(CURDIR)/_build/html/index.html"

# unit tests and the Examples sections of the package docstrings (doctests)
unit: $(STAMP)
	$(RUN) $(BIN)/python -m pytest -q $(XDIST) tests --ignore=tests/book --doctest-modules src/kftrack

nbval: $(STAMP)
	$(RUN) $(BIN)/python -m pytest -q $(XDIST) $(NBVAL) notebooks

booktest: $(STAMP)
	$(RUN) $(BIN)/python -m pytest -q tests/book

test: unit nbval booktest

# Developer check, not part of `make test`: unit tests and nbval under the OpenBLAS kernels
# Haswell, Sandybridge, Zen, SkylakeX and with NumPy's SIMD dispatch reduced (UNIT_ONLY=1: unit only).
portability: $(STAMP)
	PY=$(BIN)/python tests/portability.sh $(if $(UNIT_ONLY),--unit-only,)

lab: $(STAMP)
	$(RUN) $(BIN)/jupyter lab notebooks

NB ?= notebooks/*.ipynb
execute: $(STAMP)
	$(RUN) $(BIN)/jupyter nbconvert --to notebook --execute --inplace \
	  --ExecutePreprocessor.timeout=300 --ExecutePreprocessor.kernel_name=python3 $(NB)

# Developer check, not part of `make test` (which runs chapter 01 in JupyterLite):
# every chapter with a Lite copy run through the JupyterLite notebook interface in Debian's
# Chromium, offline, with the time of each. Builds the site first (book/_ext/lite.py makes lite/).
lite-check: book
	KFTRACK_SITE_BUILT=1 KFTRACK_LITE_CHAPTERS=all $(RUN) $(BIN)/python -m pytest -q -s tests/book/test_lite.py -k chapter_runs

# Performance appendix (not part of `make test`): the rivals are pinned in benchmarks/requirements.txt.
benchmark: $(STAMP)
	$(BIN)/python -m pip install -q -r benchmarks/requirements.txt
	$(RUN) $(BIN)/python benchmarks/filters.py
	$(RUN) $(BIN)/python benchmarks/compose.py

clean:
	rm -rf _build .pytest_cache .hypothesis
	find . -name __pycache__ -not -path './.venv/*' -prune -exec rm -rf {} +
