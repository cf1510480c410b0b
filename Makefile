# Two commands on a fresh machine: `make demo` runs the main job, `make test` runs the tests.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: install demo test lint bench gpu-check

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

# Two test processes side by side (pytest-xdist), each file whole in one of them so that its fixtures are built once:
# one process keeps about one core busy, its time going to small tensors and to waiting on its child processes.
TEST_WORKERS ?= 2
test: install
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile

# mypy's settings (the pydantic plugin, per-package overrides) are in pyproject.toml's [tool.mypy]; the packages it
# checks are the ones named here.
lint: install
	$(VENV)/bin/ruff check .
	$(PY) -m mypy api_schemas service worker symgs_core

# Every table of BENCHMARKS.md, measured at the checked-out commit (hours on 2 cores); QUICK=1: a short subset written
# to bench-out/BENCHMARKS.quick.md; ONLY=codec,decode: some entries (benchmarks/run_all.py --list names them).
bench: install
	$(PY) benchmarks/run_all.py $(if $(QUICK),--quick) $(if $(ONLY),--only $(ONLY))

# On a machine with an NVIDIA GPU and the `gpu` extra: kernels, CUDA tests, a job through the API and a GPU worker,
# the timing table against this machine's CPU and the real scenes on CUDA, within 8 minutes and offline; writes
# bench-out/gpu/gpu.md, the block BENCHMARKS.md keeps under "GPU". The real scenes are read from ../shared/data.
DATA := ../shared/data
REAL_SCENES := $(wildcard $(addprefix $(DATA)/,kacytran_try_iter7000/point_cloud.ply \
	playbot_cc_by_sa3d/playbot_lod3_31k_sh2.ply donut_mipsplatting/donut_graphdeco_sh0.ply \
	fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply padilla_captures_cc_by/plant_113k_sh0.ply \
	padilla_captures_cc_by/academic_tarot_cards_115k_sh0.ply playbot_cc_by_sa3d/playbot_lod2_125k_sh2.ply))
gpu-check: install
	$(PY) benchmarks/gpu_check.py $(if $(REAL_SCENES),--real $(REAL_SCENES)) \
		$(if $(filter %125k_sh2.ply,$(REAL_SCENES)),--base $(filter %125k_sh2.ply,$(REAL_SCENES)))
