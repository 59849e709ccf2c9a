# One entry point for set-up, tests, the demo and benchmarks. Everything runs from .venv/.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

# Spinning OpenMP waits slow torch badly when the cores are shared (see BENCHMARKS.md).
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: install lint test test-blender-versions demo bench report extension clean train-model

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

test: install
	$(PY) -m pytest -q

# The Blender tests (tests/blender) against each Blender version the manifest claims besides the
# 5.0 of the everyday suite: one venv per version under build/ with that bpy wheel from PyPI (large
# downloads) and what Refine needs; pytest runs here, the scenarios in that venv's Blender.
BLENDER_VERSIONS ?= 4.2.0 4.5.15
BLENDER_PYTHON_BIN ?= python3.11
build/bpy-%/.installed:
	test -x build/bpy-$*/bin/python || $(BLENDER_PYTHON_BIN) -m venv build/bpy-$*
	build/bpy-$*/bin/python -m pip install -q "bpy==$*" "numpy==1.26.*" torch==2.13.0 safetensors==0.8.0 \
		scipy pillow tqdm
	touch $@

test-blender-versions: install $(foreach v,$(BLENDER_VERSIONS),build/bpy-$(v)/.installed)
	set -e; for v in $(BLENDER_VERSIONS); do \
		echo "== Blender $$v"; \
		GVAE_BLENDER_PYTHON=$(CURDIR)/build/bpy-$$v/bin/python $(PY) -m pytest -q tests/blender; \
	done

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

# Reproduce the bundled lineage VAEs in models/: benchmark scenes -> progressive 3DGS runs through 2x the
# training resolution (cached, shared with `make report PROFILE=full`) -> `gvae fit-vae` with two scenes
# held out; prints how long each part took.
train-model: install
	$(PY) tools/train_model.py --out models

clean:
	rm -rf $(VENV) dist build *.egg-info .pytest_cache
