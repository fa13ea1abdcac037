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


@pytest.mark.parametrize("dtype", ["fp64", "fp32"])
@pytest.mark.parametrize("on", [True, False])
def test_the_triton_kernels_compile_for_an_h100(dtype, on):
    """Every kernel compiles ahead of time for sm_90 (triton's own ptxas; no GPU needed), with every switch
    on or off: what the interpreter does not check (types, constexpr globals, the lowering)."""
    for name in triton_profile.KERNELS + ("_tiled",):
        for axis in ((0, 1) if name == "_faces" else (None,)):
            kernel = triton_profile.compile_kernel(name, dtype, dict.fromkeys(triton_profile.switches(name), on), axis)
            assert len(kernel.asm["cubin"]) > 0, name


def test_stored_velocities_take_the_divisions_and_square_roots_out_of_the_faces():
    """With VELOCITIES = "stored" an x face reads its 8 velocities instead of dividing for each (and taking
    a square root): at least 8 fewer MUFU instructions per face in the compiled kernel, no spills."""
    pytest.importorskip("triton.backends.nvidia")
    prof = {}
    for stored in (False, True):
        kernel = triton_profile.compile_kernel("_faces", "fp32", {"STORED": stored}, axis=0, block=128, num_warps=4)
        prof[stored] = triton_profile.sass_profile(kernel, cells_per_thread=1)
    assert prof[True]["mufu_per_cell"] >= 2                     # the face's wave speeds: two sqrt, one division
    assert prof[True]["mufu_per_cell"] <= prof[False]["mufu_per_cell"] - 8, prof
    assert prof[True]["instructions_per_cell"] < prof[False]["instructions_per_cell"], prof
    assert prof[True]["local_bytes"] == prof[False]["local_bytes"] == 0, prof


def test_the_tiled_faces_compute_each_cells_work_once():
    """FACES = "tiled" computes each cell's velocities, reconstructions and pressure coefficient once per stage
    (the faces read their neighbours' from the tile) where the lines recompute them for each face: in float32
    Voellmy (the slope metric and the no-creep rule on), a fifth fewer SASS instructions per cell than the line
    design's velocities, carried velocities and x and y faces together (the halo's positions included) and
    fewer floating-point ones, with no spills."""
    pytest.importorskip("triton.backends.nvidia")
    from torchslide.solver import fused_triton

    on = triton_profile.TERMS["voellmy"]
    tiled = triton_profile.sass_profile(
        triton_profile.compile_kernel("_tiled", "fp32", on),
        triton_profile.tile_cells_per_thread(fused_triton.TILE, fused_triton.TILE_WARPS))
    lines = [triton_profile.sass_profile(triton_profile.compile_kernel(name, "fp32", {**on, "STORED": True}, axis,
                                                                       block=128, num_warps=4), 1)
             for name, axis in (("_velocities", None), ("_carried", None), ("_faces", 0), ("_faces", 1))]
    assert tiled["local_bytes"] == 0, tiled
    assert tiled["instructions_per_cell"] < 0.8 * sum(p["instructions_per_cell"] for p in lines), (tiled, lines)
    assert tiled["fp_per_cell"] < sum(p["fp_per_cell"] for p in lines), (tiled, lines)
