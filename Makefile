# Two entry points do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# OpenMP threads spin-wait on 2 cores (pyfftw, so3g): let idle threads sleep.
export OMP_WAIT_POLICY ?= passive
# glibc gives every freed array of more than 32 MB back to the kernel and faults the next one
# in page by page: a third of the tests' CPU time was the kernel's. Kept in the heap instead,
# a pipeline test module runs 9-11 % faster (its system time halved) for 10-13 % more memory
# (docs/results/performance.md).
export MALLOC_MMAP_THRESHOLD_ ?= 4294967296
export MALLOC_TRIM_THRESHOLD_ ?= 17179869184
export MALLOC_TOP_PAD_ ?= 1073741824
# numpy asks the kernel for huge pages on every array above 4 MB; with this kernel's
# `defrag=madvise` each such fault may compact memory first. Off, a pipeline test module
# spends 3 s in the kernel instead of 17 and runs a quarter faster (docs/results/performance.md).
export NUMPY_MADVISE_HUGEPAGE ?= 0

.PHONY: demo test test-slow test-fast test-py313 install-py313 lint docs bench bench-site clean install

# -qq: pip's errors only (its warnings about index locations this machine's pip
# configuration names but lacks are noise here)
PIP    := $(PY) -m pip install -qq --disable-pip-version-check

$(STAMP): pyproject.toml constraints.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	@echo "installing the environment in $(VENV) (first use only)"
	@$(PIP) --upgrade pip
	@$(PIP) -e '.[test,docs]' -c constraints.txt   # CI's exact set (pyproject.toml: ranges)
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/so-transients demo --config configs/sim_demo.yaml --out data/demo

# One worker per core, each running whole test modules (their module-scoped datasets are
# simulated once); `pytest` alone runs them one at a time. One thread per worker: BLAS and
# OpenMP threads of two workers on two cores only contend.
XDIST  := -n auto --dist loadfile
THREADS := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
test: $(STAMP)
	$(THREADS) $(PY) -m pytest $(XDIST)

# The end-to-end tests alone.
test-slow: $(STAMP)
	$(THREADS) $(PY) -m pytest $(XDIST) -m slow

# The quick subset for development: everything but the end-to-end tests marked `slow`.
test-fast: $(STAMP)
	$(THREADS) $(PY) -m pytest $(XDIST) -m "not slow"

# The quick subset again on Python 3.13, the newest interpreter the dependency ranges admit
# (SO's environments beside sotrplib are 3.12+), in its own environment .venv313.
PY313 ?= $(shell pyenv which python3.13 2>/dev/null || PYENV_VERSION=3.13 pyenv which python 2>/dev/null || command -v python3.13)
install-py313:
	@test -x .venv313/bin/python || $(PY313) -m venv .venv313
	@.venv313/bin/python -m pip install -qq --disable-pip-version-check -e '.[test,docs]' -c constraints.txt

PY313_WORKERS ?= auto
test-py313: install-py313
	$(THREADS) .venv313/bin/python -m pytest -n $(PY313_WORKERS) --dist loadfile -m "not slow" -p no:cacheprovider

# ruff, configured in pyproject.toml
lint: $(STAMP)
	$(VENV)/bin/ruff check so_transients tests benchmarks studies docs

# The documentation (docs/), warnings as errors; open docs/_build/html/index.html
docs: $(STAMP)
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html docs docs/_build/html

# Speed and memory of the detection chain against the FFT floor (prints a table; see README).
bench: $(STAMP)
	$(PY) benchmarks/bench_chain.py --json bench_chain.json

# The whole production site pipeline (sotodlib's steps and ours) on one hour of one wafer-band,
# then several groups under 1, 2 and 3 MPI ranks; prints the LAT-scale cores and memory.
bench-site: $(STAMP)
	$(PY) benchmarks/bench_site.py --json bench_site.json
	$(PY) benchmarks/bench_site.py --mpi --json bench_site_mpi.json

clean:
	rm -rf data out results .pytest_cache docs/_build
