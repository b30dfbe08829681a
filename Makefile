# kohpymc: two commands on a fresh machine (Python 3.11 + make).
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# One BLAS thread: the matrices here are small, and on a shared 2-core machine OpenBLAS's
# spinning worker threads made a GP calibration 4x slower (174 s vs 44 s, beam M4).
export OPENBLAS_NUM_THREADS ?= 1

BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: demo test test-slow bench bench-mass-matrix bench-discovery bench-discovery-mcmc bench-slow-simulator bench-dielectric-emulator lint format typecheck clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/kohpymc study kohpymc/examples/beam_study.toml --out out/beam_study

test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile --durations=20

test-slow: $(STAMP)
	$(PY) -m pytest -m slow

$(BENCH_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e ".[dev,bench]"
	@touch $(BENCH_STAMP)

# kohpymc vs random-walk Metropolis and surmise, study wall time, n = 9,120 GP (~20 min),
# time to a usable posterior (ESS >= 1000, r_hat <= 1.01; ~1 h, plus up to ~2 h for the dielectric
# stand-in M0-M5); tables in benchmarks/results/
bench: $(BENCH_STAMP)
	$(PY) -m benchmarks.run

# nutpie's diagonal against its low-rank mass-matrix adaptation on the beam and the hard
# posteriors (~10 min); table in benchmarks/results/mass_matrix.md
bench-mass-matrix: $(BENCH_STAMP)
	$(PY) -m benchmarks.mass_matrix

# hidden-effect benchmark of discovery: 16 kinds of missing effect x 2 noise levels x 2 seeds
# and 64 null data sets, noise sd given and unknown, STLSQ baseline (~15 min on 2 busy cores);
# tables in benchmarks/results/discovery.md
bench-discovery: $(STAMP)
	$(PY) -m benchmarks.discovery --seeds 2 --null-seeds 8

# the full discover (two MCMC runs each) on six kinds of missing effect and two null models
bench-discovery-mcmc: $(STAMP)
	$(PY) -m benchmarks.discovery --mcmc --draws 500 --chains 2

# a simulator sleeping 1 s per call: the direct study's cost (its calls counted on a
# non-sleeping copy) against the emulated study (150 runs) on a 2-worker LocalCluster and
# in-process (~10 min); table in benchmarks/results/slow_simulator.md
bench-slow-simulator: $(STAMP)
	$(PY) -m benchmarks.slow_simulator

# the dielectric stand-in (M0) through the principal-component emulator, 250 + 50 runs, against a
# direct calibration (first target: the direct run, ~1 h on 2 busy cores; then the emulated one,
# a few minutes); table in benchmarks/results/dielectric_emulator.md
bench-dielectric-emulator: $(STAMP)
	@test -f benchmarks/results/dielectric_direct_M0.nc || $(PY) -m benchmarks.dielectric_emulator --direct-only --direct benchmarks/results/dielectric_direct_M0.nc
	$(PY) -m benchmarks.dielectric_emulator --direct benchmarks/results/dielectric_direct_M0.nc

LINT_PATHS := kohpymc tests benchmarks notebooks tools

lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINT_PATHS)
	$(VENV)/bin/ruff format --check $(LINT_PATHS)

format: $(STAMP)
	$(VENV)/bin/ruff format $(LINT_PATHS)
	$(VENV)/bin/ruff check --fix $(LINT_PATHS)

# mypy on kohpymc: fails if a file has more errors than tools/typecheck_baseline.json allows
# (`$(PY) tools/typecheck.py --update` rewrites the baseline once errors are fixed)
typecheck: $(STAMP)
	$(PY) tools/typecheck.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
