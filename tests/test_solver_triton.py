"""The Triton step against the torch step under Triton's interpreter (tests/triton_interpret.py: one case
per process, since the interpreter is chosen when triton is imported); every output of short whole runs
equal to round-off in float64 and within 1e-5 in float32. On a GPU, tests/test_gpu.py runs the compiled
kernels against eager on the verification cases."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench import triton_profile

from . import triton_interpret

pytest.importorskip("triton")

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("case", sorted(triton_interpret.CASES))
def test_triton_step_equals_the_torch_step(case):
    env = dict(os.environ, TRITON_INTERPRET="1", OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-m", "tests.triton_interpret", case], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "equals the torch step" in run.stdout


def test_fast_float32_stays_finite_when_subnormals_flush_to_zero():
    env = dict(os.environ, TRITON_INTERPRET="1", OMP_NUM_THREADS="1", **triton_interpret.SETTINGS["flushed_float32"])
    env.pop("TORCHSLIDE_EXACT_FLOAT32", None)
    run = subprocess.run([sys.executable, "-m", "tests.triton_interpret", "flushed_float32"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]


def test_the_triton_step_is_chosen_on_cuda_or_under_the_interpreter(monkeypatch):
    from torchslide.solver import fused_triton
    from torchslide.solver.stepping import StepFlags

    F = StepFlags(dx=40.0, g=9.81, cfl=0.45, theta=1.3, h_eps=1e-3, h_wet=1e-4, wb_ratio=0.25, dt_max=1.0,
                  stop_ke_fraction=1e-4, arrival_threshold=0.1, v_max_min_depth=0.05, entrain_h_min=0.01,
                  no_creep=True, slope_correction=True, use_ep=True, use_curv=True, use_ent=True, use_dep=True,
                  use_mu_i=True, use_mu_scale=True, domain="wall")
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    assert fused_triton.supported(F, "cuda") is None
    assert "CUDA" in fused_triton.supported(F, "cpu")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    assert fused_triton.supported(F, "cpu") is None


def test_the_marching_band_shortens_for_small_batches_on_a_card_of_132_multiprocessors(monkeypatch):
    """band on the 20 m Bondo-like grid (100 x 325) for the marching faces (28 columns a strip) on an H100/H200
    (132 multiprocessors): a band of 64 rows only where the batch gives every multiprocessor 8 programs; off
    CUDA the whole BAND, and the card's count is read once per device."""
    import torch

    from torchslide.solver import fused_triton

    calls = []

    def properties(device):
        calls.append(device)
        return type("Properties", (), {"multi_processor_count": 132})()

    fused_triton.multiprocessors.cache_clear()
    monkeypatch.setattr(torch.cuda, "get_device_properties", properties)
    try:
        rows = [fused_triton.band((32, 64), B, 100, 325, 28, "cuda") for B in (1, 10, 32, 256)]
        assert rows == [8, 8, 32, 64]
        assert len(calls) == 1
        assert fused_triton.band((32, 64), 1, 100, 325, 28, "cpu") == 64
    finally:
        fused_triton.multiprocessors.cache_clear()


@pytest.mark.parametrize("dtype", ["fp64", "fp32"])
def test_the_triton_kernels_compile_for_an_h100(dtype):
    """Every kernel of both designs of the faces compiles ahead of time for sm_90 (triton's own ptxas; no GPU
    needed) with every switch on: what the interpreter does not check (types, constexpr globals, the lowering),
    and no spills to local memory. (A default Voellmy run's switches compile in
    test_the_marching_step_takes_at_most_1500_instructions_per_float32_cell_update; the second stage's faces are
    a constexpr subset of the first's.)"""
    names = {name for kernels in triton_profile.KERNELS.values() for name, _ in kernels if "+second" not in name}
    for name in sorted(names):
        kernel = triton_profile.compile_kernel(name, dtype, dict.fromkeys(triton_profile.switches(name), True))
        assert len(kernel.asm["cubin"]) > 0, name
        assert triton_profile.sass_profile(kernel, 1)["local_bytes"] == 0, name


def _step_counts(design: str, dtype: str = "fp32", terms: str = "voellmy") -> dict:
    """bench.triton_profile's per cell-update counts of one design (a default Voellmy run's switches)."""
    from torchslide.solver import fused_triton

    rows = []
    for name, runs in triton_profile.KERNELS[design]:
        switched = triton_profile.TERMS[terms]
        on = {s: (s not in triton_profile.SKIP) if switched is None else switched.get(s, False)
              for s in triton_profile.switches(name)}
        kernel = triton_profile.compile_kernel(name, dtype, on)
        if name.startswith("_march"):
            w, rows_ = fused_triton.MARCH
            prof = triton_profile.sass_profile(kernel, (w - 4) / 32, (rows_, rows_ + 1, fused_triton.MARCH_UNROLL))
        elif name.startswith("_update"):
            w, rows_ = fused_triton.UPDATE
            prof = triton_profile.sass_profile(kernel, (w - 2) / 32, (rows_, rows_, fused_triton.UPDATE_UNROLL))
        else:
            prof = triton_profile.sass_profile(kernel, triton_profile.default_block(dtype) // (32 * fused_triton.NUM_WARPS))
        assert prof["local_bytes"] == 0, (name, prof)
        rows.append({"kernel": name, "runs_per_step": runs, "design": design, "dtype": dtype, "terms": terms, **prof})
    return triton_profile.per_cell_update(rows)[f"{design}-{dtype}-{terms}"]


def test_the_marching_step_takes_at_most_1500_instructions_per_float32_cell_update():
    """The marching design computes each cell's slopes and each face's flux once per stage, with no barrier: a
    float32 Voellmy cell-update (two stages of the faces and the update, the slope metric and the no-creep rule
    on) compiles for sm_90 to at most 1,500 SASS instructions, no spills (bench/results/triton_profile.json has
    every design, dtype and set of terms)."""
    pytest.importorskip("triton.backends.nvidia")
    assert _step_counts("march")["instructions"] <= 1500
