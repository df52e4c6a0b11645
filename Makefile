# `make demo` runs the main job, `make test` the test suite; both create .venv on first use.
# The pinned torch is installed first so that the `torch>=2.2` range does not pull a CUDA build;
# override it elsewhere, e.g. `make test TORCH=torch`.
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test bench clean

$(VENV)/.installed: pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)" setuptools wheel ninja
	# --no-build-isolation: the native kernels build against the torch just installed (setup.py)
	$(PY) -m pip install -q --no-build-isolation -e ".[test,experiments]"
	touch $@

demo: $(VENV)/.installed
	$(PY) -m experiments.fit.fit_texture --out results/fit_texture

test: $(VENV)/.installed
	$(PY) -m pytest tests

bench: $(VENV)/.installed
	$(PY) -m experiments.bench.bench_sample

clean:
	rm -rf $(VENV) results
