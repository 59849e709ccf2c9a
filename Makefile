# One entry point for set-up, tests, the demo and benchmarks. Everything runs from .venv/.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

# Spinning OpenMP waits slow torch badly when the cores are shared (see BENCHMARKS.md).
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: install lint test test-blender-versions test-numpy2 demo bench report extension clean train-model

install: $(STAMP)

# Re-runs only when the dependency list changes; a second `make install` does nothing.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[blender,test]"
	touch $(STAMP)

# ruff, configured in pyproject.toml ([tool.ruff]).
lint: install
	$(PY) -m ruff check .

# Four streams of about equal CPU time keep the 2 cores busy to the end, each suite in its own
# temporary folder, the logs of the three in the background following: the tests that never render
# (file formats, the Blender-made scenes, the documents), then a part of the core suite; beside them
# the compiled CPU kernels made ready (compiled once per machine, ~20 s on one core; then loaded) so
# that no later process compiles its own, then the rest of the core suite; the Blender tests in two
# halves (what Cycles and EEVEE show; the rest). One thread per process: four processes on two cores
# spend less CPU than four that each spin two threads.
NO_RENDER := tests/test_splat_transform.py tests/test_scenes.py tests/test_ply.py tests/test_formats.py \
	tests/test_sog.py tests/test_docs.py
CORE_LATE := tests/test_kernels.py tests/test_sfm.py tests/test_hessian.py
BLENDER_DISPLAY := tests/blender/test_display.py
test: export OMP_NUM_THREADS := 1
test: export OPENBLAS_NUM_THREADS := 1
test: export MKL_NUM_THREADS := 1
test: export NUMBA_NUM_THREADS := 1
test: install
	@mkdir -p build
	@($(PY) -m pytest -q --basetemp=build/pytest-files $(NO_RENDER); first=$$?; \
	  $(PY) -m pytest -q --basetemp=build/pytest-late $(CORE_LATE) && test $$first -eq 0) \
		> build/test-files.log 2>&1 & b0=$$!; \
	$(PY) -c "from gvae_core.warmup import main; main()"; \
	$(PY) -m pytest -q --basetemp=build/pytest-blender tests/blender --ignore=$(BLENDER_DISPLAY) \
		> build/test-blender.log 2>&1 & b1=$$!; \
	$(PY) -m pytest -q --basetemp=build/pytest-display $(BLENDER_DISPLAY) > build/test-display.log 2>&1 & b2=$$!; \
	$(PY) -m pytest -q --basetemp=build/pytest-core --ignore=tests/blender $(NO_RENDER:%=--ignore=%) \
		$(CORE_LATE:%=--ignore=%); core=$$?; \
	wait $$b0; files=$$?; wait $$b1; blender=$$?; wait $$b2; display=$$?; \
	echo "--- $(NO_RENDER) $(CORE_LATE) and tests/blender (ran beside the above):"; \
	cat build/test-files.log build/test-blender.log build/test-display.log; \
	test $$core -eq 0 && test $$files -eq 0 && test $$blender -eq 0 && test $$display -eq 0

# The Blender tests (tests/blender) against each Blender version the manifest claims: the everyday
# 5.0.1 in .venv, the others each in a venv under build/ with that bpy wheel from PyPI (~0.4 GB each)
# and what Refine needs; pytest runs here, the scenarios in that venv's Blender. Blender up to 5.0 runs
# Python 3.11 with numpy 1.26 (torch: the CPU build from local disk); 5.1 and later run Python 3.13 with
# numpy 2 (2.3, the VFX Reference Platform 2026's, as Blender ships it) and get no torch here: PyPI's
# Linux torch for cp313 is the CUDA build, so the Refine job test says so and skips there.
BLENDER_VERSIONS ?= 4.2.0 4.5.15 5.0.1 5.1.2 5.2.3 5.3.0
BLENDER_EVERYDAY := 5.0.1
PYTHON311 ?= python3.11
PYTHON313 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.13*/bin/python3.13) python3.13)
py313 = $(filter-out 4.% 5.0.%,$(1))
build/bpy-%/.installed:
	test -x build/bpy-$*/bin/python || $(if $(call py313,$*),$(PYTHON313),$(PYTHON311)) -m venv build/bpy-$*
	build/bpy-$*/bin/python -m pip install -q "bpy==$*" safetensors==0.8.0 numba==0.68.1 scipy pillow tqdm \
		$(if $(call py313,$*),"numpy==2.3.*","numpy==1.26.*" torch==2.13.0)
	touch $@

test-blender-versions: install $(foreach v,$(filter-out $(BLENDER_EVERYDAY),$(BLENDER_VERSIONS)),build/bpy-$(v)/.installed)
	set -e; for v in $(BLENDER_VERSIONS); do \
		echo "== Blender $$v"; \
		py=build/bpy-$$v/bin/python; [ $$v != $(BLENDER_EVERYDAY) ] || py=$(PY); \
		GVAE_BLENDER_PYTHON=$(CURDIR)/$$py $(PY) -m pytest -q tests/blender; \
	done

# gvae_core (the whole suite but tests/blender) under numpy 2 (2.3, as Blender 5.1+ ships it), in
# build/numpy2; `make test` runs it under numpy 1.26 (bpy 5.0.1 needs numpy < 2).
build/numpy2/.installed: pyproject.toml
	test -x build/numpy2/bin/python || $(PYTHON311) -m venv build/numpy2
	build/numpy2/bin/python -m pip install -q -e ".[test]" "numpy==2.3.*"
	touch $@

test-numpy2: build/numpy2/.installed
	build/numpy2/bin/python -m pytest -q --ignore=tests/blender

demo: install
	$(PY) -m gvae_core demo

bench: install
	$(PY) -m gvae_core.benchmarks

# The paper's experiment on the benchmark scenes -> reports/ (README.md, results.json, plots).
# PROFILE=full: all six scenes at the benchmark resolution (hours), into reports/full/.
PROFILE ?= quick
report: install
	$(PY) -m gvae_core report --profile $(PROFILE) --out reports$(if $(filter-out quick,$(PROFILE)),/$(PROFILE))

# Blender extension zip into dist/ (built and validated with Blender's blender_ext.py).
# TORCH_WHEELS=DIR also bundles a folder of torch + dependency wheels for one platform (offline).
extension: install
	$(PY) tools/build_extension.py $(if $(TORCH_WHEELS),--torch-wheels $(TORCH_WHEELS))

# Reproduce the bundled detail model in models/: seeded variants of the training scenes -> progressive 3DGS
# runs to the quick protocol's training resolution (cached) -> training through the renderer against their
# real 1.5x/2x images, scored on the validation scenes; prints how long each part took.
# MODEL=vae: the lineage VAEs (the full protocol's runs -> `gvae fit-vae`, hours).
MODEL ?= detail
train-model: install
	$(PY) tools/train_model.py --model $(MODEL) --out models

clean:
	rm -rf $(VENV) dist build *.egg-info .pytest_cache
