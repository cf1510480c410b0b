# Two commands on a fresh machine: `make demo` runs the main job, `make test` runs the tests.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: install demo test lint bench

install: $(VENV)/.installed

# torch is installed first and pinned: the project's own range accepts it, so pip pulls no other build.
$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e ".[dev]"
	touch $@

demo: install
	$(VENV)/bin/symgs demo

test: install
	$(PY) -m pytest

lint: install
	$(VENV)/bin/ruff check .
