# torchslide: set-up, demo, tests and benchmarks. Every target bootstraps .venv itself.
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv demo diagnose-demo test test-all test-gpu bench bench-solver bench-solver-gpu bench-triton-profile bench-inference bench-executor bench-diagnose bench-coverage clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[dev]"
	$(PY) -m torchslide.solver.warm   # the fused steps (CPU; CUDA where there is one), compiled once into their caches
	touch $(STAMP)

demo: $(STAMP)
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-2} $(PY) -m experiments.demo --out demo_out

# The diagnose CLI on files: one blind harness case (entrainment, seed 1) written as DEM / maps / gauge CSVs
# + diagnose.toml (experiments/hidden_physics/export_case.py), then `torchslide diagnose` on them; one torch
# thread, as the harness runs (faster on these small grids, and the same result as the harness case).
diagnose-demo: $(STAMP)
	$(PY) -m experiments.hidden_physics.export_case entrainment 1 --out diagnose_demo
	OMP_NUM_THREADS=1 $(VENV)/bin/torchslide diagnose diagnose_demo/diagnose.toml \
		--out diagnose_demo/diagnosis

# Tests run on every core (pytest-xdist, an idle worker taking queued tests from a busy one), one torch thread per
# worker.
test: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n auto --dist worksteal --timeout=900 --durations=15

test-all: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n auto --dist worksteal -m "" --timeout=3600 --durations=15

# the CUDA checks alone (tests/test_gpu.py; skipped where torch sees no GPU), on a GPU machine
test-gpu: $(STAMP)
	$(PY) -m pytest -q tests/test_gpu.py -m "" --timeout=1800 --durations=10

bench: bench-solver bench-triton-profile bench-inference bench-executor bench-diagnose bench-coverage

bench-solver: $(STAMP)
	$(PY) -m bench.bench_solver --out bench/results/solver.json --batches 1,8,32 --repeats 3 --t-short 5 \
		--full-batch 8 --full-configs eager-f64-whole:1,eager-f64-crop,fused-f64-crop,fused-f32-crop,compiled-f64-crop,compiled-f32-crop,compiled-f32-crop:32
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-2} $(PY) -m bench.bench_solver --terrain msh2021 --mu 0.4 --xi 2500 --skip-throughput \
		--kernels eager,fused --full-configs fused-f64-crop,eager-f64-crop,fused-f64-crop:1 --full-repeats 3 --out bench/results/solver_msh2021.json
	OMP_NUM_THREADS=1 $(PY) -m bench.stop_rule --cellsize 40 --out bench/results/stop_rule.json

# on a CUDA machine: eager and fused, float32 and float64, batch 1, 32 and 256, with and without CUDA graphs, the
# line design of the faces beside the marching default (BLOCKxWARPS:lines), each row with its fraction of the card's
# copy bandwidth; and the small batch of an active-learning call, 10 members for 300 s simulated, with and without
# graphs (add compiled with KERNELS=eager,compiled,fused: its first call compiles for minutes)
KERNELS ?= eager,fused
bench-solver-gpu: $(STAMP)
	$(PY) -m bench.bench_solver --device cuda --out bench/results/solver_gpu.json --kernels $(KERNELS) \
		--batches 1,32,256 --graphs on,off --launch 512x4:lines --repeats 3 --t-short 10 \
		--full-configs fused-f32-crop:10,fused-f32-crop:10:graphs,fused-f64-crop:10 --full-repeats 3

# registers, spills and SASS instructions per cell of every Triton kernel, compiled for an H100/H200 on the CPU
bench-triton-profile: $(STAMP)
	$(PY) -m bench.triton_profile --arch 90 --out bench/results/triton_profile.json
	TORCHSLIDE_EXACT_FLOAT32=1 $(PY) -m bench.triton_profile --arch 90 --out bench/results/triton_profile_exact_float32.json

bench-inference: $(STAMP)
	$(PY) -m pip install -q -e ".[bench]" || echo "pyvbmc not installable: its comparison is skipped"
	OMP_NUM_THREADS=1 $(PY) -m bench.bench_inference --quick --seeds 5 --out bench/results/inference.json

# a 256-run sweep in this process and on a Dask LocalCluster of 1 and 2 workers (one torch thread each)
bench-executor: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m bench.bench_executor --out bench/results/executor.json

# one `torchslide diagnose` case as a user runs it (40 m, deposit map, 2 gauges): wall time and report.json's
# time per stage, a null and an entrainment case, on 2 torch threads unless OMP_NUM_THREADS says otherwise
bench-diagnose: $(STAMP)
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-2} $(PY) -m bench.bench_diagnose --out bench/results/diagnose_case.json

# coverage of the 90 % intervals on synthetic cases the calibrated model cannot reproduce exactly (a finer grid,
# a missing term, a release error, a smoothed DEM), with and without the learnt discrepancy: 64 calibrations on
# COVERAGE_WORKERS processes (2 by default, one torch thread each), every case measured anew
# (COVERAGE_RESUME=--resume keeps the cases already in the JSON: an interrupted run continues)
bench-coverage: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m bench.coverage --out bench/results/coverage.json --workers $${COVERAGE_WORKERS:-2} \
		$${COVERAGE_RESUME:-}

clean:
	rm -rf $(VENV) demo_out diagnose_demo .pytest_cache
