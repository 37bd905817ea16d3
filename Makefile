# Every target creates or reuses the local virtual environment .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
WORKDIR ?= workdirs/demo
JOBS ?= 2

.PHONY: venv demo test test-slow bench-render clean

venv: $(STAMP)

$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=$(WORKDIR)

test: $(STAMP)
	$(PY) -m pytest -n $(JOBS) -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -p no:xdist -m slow

bench-render: $(STAMP)
	$(PY) -m experiments.bench_render --out=experiments/results $(BENCH_ARGS)

clean:
	rm -rf workdirs .pytest_cache
