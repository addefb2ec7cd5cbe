# Two entry points do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# OpenMP threads spin-wait on 2 cores (pyfftw, so3g): let idle threads sleep.
export OMP_WAIT_POLICY ?= passive

.PHONY: demo test bench clean install

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/so-transients demo --config configs/sim_demo.yaml --out data/demo

test: $(STAMP)
	$(PY) -m pytest

# Speed and memory of the detection chain against the FFT floor (prints a table; see README).
bench: $(STAMP)
	$(PY) benchmarks/bench_chain.py --json bench_chain.json

clean:
	rm -rf data out results .pytest_cache
