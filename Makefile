# One entry point for set-up, tests, the demo and benchmarks. Everything runs from .venv/.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install test demo bench extension clean

install: $(STAMP)

# Re-runs only when the dependency list changes; a second `make install` does nothing.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[blender,test]"
	touch $(STAMP)

test: install
	$(PY) -m pytest -q

demo: install
	$(PY) -m gvae_core demo

bench: install
	$(PY) -m gvae_core.benchmarks

clean:
	rm -rf $(VENV) dist build *.egg-info .pytest_cache
