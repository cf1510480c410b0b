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

# mypy's settings (the pydantic plugin, per-package overrides) are in pyproject.toml's [tool.mypy]; the packages it
# checks are the ones named here.
lint: install
	$(VENV)/bin/ruff check .
	$(PY) -m mypy api_schemas service worker symgs_core

# Every table of BENCHMARKS.md, measured at the checked-out commit (hours on 2 cores); QUICK=1: a short subset written
# to bench-out/BENCHMARKS.quick.md; ONLY=codec,decode: some entries (benchmarks/run_all.py --list names them).
bench: install
	$(PY) benchmarks/run_all.py $(if $(QUICK),--quick) $(if $(ONLY),--only $(ONLY))
