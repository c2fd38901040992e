# The README's two commands: `make run` and `make test`. Both build .venv from nothing when it
# is missing. torch==2.13.0 goes in first: it is the CPU build, and any other torch requirement
# would pull a CUDA build of several GB.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# The console's test drives Debian's chromium; installed here when missing (as root, or with
# sudo), never downloaded by Playwright.
BROWSER := $(VENV)/.browser-stamp
RUN_OUT ?= runs/default

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev,viz,cluster]'
	touch $(STAMP)

$(BROWSER):
	command -v chromium >/dev/null || { \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q chromium; }
	command -v chromium >/dev/null
	mkdir -p $(VENV) && touch $@

run: $(STAMP)
	$(BIN)/rovergate run --out $(RUN_OUT)

# ruff, mypy and the manual's strict build (a broken link or a missing page fails), then
# the fast tests first, so that a failure shows in a minute or two; then the end-to-end tests.
# Both two at a time (the fast ones 1:41 became 1:15; most of the end-to-end tests' time is
# processes starting and waiting on each other).
test: $(STAMP) $(BROWSER)
	$(BIN)/ruff check .
	$(BIN)/mypy
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet --site-dir $(VENV)/site
	$(BIN)/python -m pytest -q -m 'not e2e' -n 2
	$(BIN)/python -m pytest -q -m e2e -n 2

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_loop.py

clean:
	rm -rf $(VENV) runs .pytest_cache
