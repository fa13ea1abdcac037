"""The fused CPU step (torchslide.solver.fused_cpu) against the torch step, the oracle: every output of
whole runs equal to round-off in float64 and within 1e-5 relative in float32, with each term it covers
on, on curved terrain in map coordinates (a channel with bends, the dip off the grid axes)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain.synthetic import channel_with_bends, release_from_shape

from .conftest import cap_release, tilted_plane

pytest.importorskip("numba")

FIELDS = ("h_max", "v_max", "h_final", "arrival_time", "final_volume", "outflow_volume", "mass_history",
          "ke_history", "t_final")


def _channel():
    """A 40 m channel with two bends (50 x 20 cells), a release at its top and a gauge on its thalweg."""
    dem = channel_with_bends(cellsize=40.0, theta_deg=25.0, slope_length=1600.0, runout_length=400.0, width=800.0)
    rel = release_from_shape(dem, (300.0, 400.0), 80.0, volume=5.0e4)
    j = int(900.0 / dem.cellsize)
    y = dem.yll + (int(np.argmin(dem.z[:, j])) + 0.5) * dem.cellsize
    return dem, rel, [("g1", 900.0 + 0.5 * dem.cellsize, y)]


def _compare(dem, rel, params: dict, cfg: SolverConfig, gauges=None, t_end: float = 60.0, rtol: float = 1e-12,
             dtype=torch.float64, mu_scale=None, erodible_depth=None):
    """Run ``cfg`` with kernel "eager" (the reference) and "fused"; every output must agree within ``rtol``
    of its largest magnitude. Returns the reference result."""
    p = Params.make(dtype=dtype, **params)
    kw = dict(t_end=t_end, gauges=gauges, dtype=dtype, mu_scale=mu_scale, erodible_depth=erodible_depth)
    ref = simulate(dem, rel, p, config=dataclasses.replace(cfg, kernel="eager"), **kw)
    new = simulate(dem, rel, p, config=dataclasses.replace(cfg, kernel="fused"), **kw)
    assert torch.equal(ref.steps, new.steps) and torch.equal(ref.stopped, new.stopped) and not new.failed.any()
    fields = FIELDS + (("entrained_volume", "bed_change") if erodible_depth is not None else ())
    for k in fields:
        a, b = getattr(ref, k), getattr(new, k)
        fin = torch.isfinite(a)
        assert torch.equal(fin, torch.isfinite(b)), k
        scale = float(a[fin].abs().max()) if fin.any() else 1.0
        if "volume" in k:       # measured against what there is to lose or gain, not its own round-off
            scale = max(scale, float(ref.release_volume.max()))
        assert float((a[fin] - b[fin]).abs().max()) <= rtol * max(scale, 1e-30), k
    for g in (gauges or []):    # against the run's largest thickness and speed (a gauge the flow never reaches
        for q, whole in (("h", ref.h_max), ("speed", ref.v_max)):   # records round-off dust)
            a, b = getattr(ref.gauges[g[0]], q), getattr(new.gauges[g[0]], q)
            assert float((a - b).abs().max()) <= rtol * float(whole.abs().max()), (g[0], q)
    return ref


def test_fused_step_equals_the_torch_step_on_a_curved_channel():
    dem, rel, gauges = _channel()
    ref = _compare(dem, rel, {"mu": [0.2, 0.25, 0.3], "xi": [500.0, 1000.0, 2000.0]}, SolverConfig(), gauges)
    assert float(ref.v_max.max()) > 10.0      # the flow moves and reaches the bends


@pytest.mark.parametrize("terms", [
    {"tau_y": 2.0},
    {"earth_pressure": [0.0, 0.5, 1.0], "phi_int": 35.0},
    {"curvature": [0.5, 1.0, 0.0]},
    {"mu_i": [0.1, 0.3, 0.0]},
    {"k_ap": 1.5, "xi": float("inf")},
])
def test_fused_step_equals_the_torch_step_with_each_term(terms):
    dem, rel, gauges = _channel()
    params = {"mu": [0.2, 0.25, 0.3], "xi": 800.0, **terms}
    _compare(dem, rel, params, SolverConfig(), gauges)


def test_fused_step_equals_the_torch_step_on_a_plane_off_the_grid_axes_and_settings():
    """A tilted plane in map coordinates with its dip 30 degrees off the grid; an open boundary, no slope
    metric, no no-creep rule, a friction map, float32."""
    dem = tilted_plane(32, 10.0, 35.0, plan_deg=30.0)[0]
    rel = cap_release(dem, -80.0, -50.0, 60.0, 4.0)
    params, open_run = compare_plane_settings(dem, rel, t_end=14.0)
    assert float(open_run.outflow_volume.min()) > 0          # both members leave through the open boundary
    _compare(dem, rel, params, SolverConfig(), t_end=14.0, dtype=torch.float32, rtol=1e-5)


def compare_plane_settings(dem, rel, t_end: float, config=SolverConfig) -> tuple:
    """_compare on a plane with an open boundary, without the slope metric and the no-creep rule, and with
    a friction map (lower on the left half); ``config`` makes the SolverConfig. Returns the two members'
    parameters and the reference run with the open boundary."""
    params = {"mu": [0.3, 0.4], "xi": [400.0, 1500.0]}
    open_run = _compare(dem, rel, params, config(boundary="open"), t_end=t_end)
    _compare(dem, rel, params, config(slope_correction=False, no_creep=False), t_end=t_end)
    ms = np.ones(dem.shape)
    ms[:, : dem.shape[1] // 2] = 0.8
    _compare(dem, rel, params, config(), t_end=t_end, mu_scale=ms)
    return params, open_run


@pytest.mark.parametrize("terms", [{"kappa": [0.002, 0.0, 0.004]}, {"deposition": [0.2, 0.0, 0.4]},
                                   {"kappa": 0.002, "deposition": 0.3}])
def test_fused_step_equals_the_torch_step_on_a_moving_bed(terms):
    """Entrainment and deposition: the bed evolves, so the geometry is recomputed every stage."""
    dem, rel, gauges = _channel()
    p = {"mu": [0.2, 0.25, 0.3], "xi": 800.0, **terms}
    ref = _compare(dem, rel, p, SolverConfig(), gauges, erodible_depth=np.full(dem.shape, 0.5))
    assert float(ref.entrained_volume.max() if "kappa" in terms else ref.h_final.max()) > 0


@pytest.mark.parametrize("nodata", ["outflow", "wall"])
def test_fused_step_equals_the_torch_step_with_cells_outside_the_domain(nodata):
    from torchslide.terrain.grid import DEM

    dem, rel, gauges = _channel()
    outside = np.zeros(dem.shape, dtype=bool)
    outside[:, 35:38] = True                 # a band of nodata across the run-out path
    outside[12:, 30:] = True
    dem = DEM(dem.z, dem.cellsize, outside=outside)
    _compare(dem, rel, {"mu": [0.15, 0.25], "xi": 1500.0}, SolverConfig(nodata=nodata), gauges)


def test_the_fused_kernel_is_chosen_where_numba_runs():
    from torchslide.solver import fused_cpu
    from torchslide.solver.stepping import StepFlags

    F = StepFlags(dx=40.0, g=9.81, cfl=0.45, theta=1.3, h_eps=1e-3, h_wet=1e-4, wb_ratio=0.25, dt_max=1.0,
                  stop_ke_fraction=1e-4, arrival_threshold=0.1, v_max_min_depth=0.05, entrain_h_min=0.01,
                  no_creep=True, slope_correction=True, use_ep=True, use_curv=True, use_ent=True, use_dep=True,
                  use_mu_i=True, use_mu_scale=True, domain="wall")
    assert fused_cpu.supported(F, "cpu") is None
    assert "CPU" in fused_cpu.supported(F, "cuda")
    with pytest.raises(ValueError, match="kernel"):
        SolverConfig(kernel="triton").validate()


def test_the_torch_step_divides_by_no_python_number():
    """torch on CUDA computes tensor / Python number as tensor * (1 / number), the CPU divides: the torch
    step writes such divisions as multiplications by the reciprocal, so that it is the same on both
    devices and the fused kernels can follow it to the last bit. Every candidate term on."""
    import math
    import traceback

    from torch.overrides import TorchFunctionMode

    from .conftest import all_terms_case

    divisions = {torch.Tensor.__truediv__, torch.Tensor.__itruediv__, torch.Tensor.div, torch.Tensor.div_,
                 torch.div, torch.true_divide}
    found = {}

    class Watch(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            if (func in divisions and len(args) > 1 and isinstance(args[1], (int, float))
                    and args[0].is_floating_point() and math.frexp(float(args[1]))[0] != 0.5):  # not a power of 2
                at = [f for f in traceback.extract_stack()[:-1] if "torchslide" in f.filename][-1]
                found[f"{at.filename.rsplit('/', 1)[-1]}:{at.lineno}"] = at.line
            return func(*args, **(kwargs or {}))

    dem, rel, p, kw = all_terms_case()
    with Watch():
        r = simulate(dem, rel, p, t_end=2.0, config=SolverConfig(kernel="eager"), **kw)
    assert float(r.v_max.max()) > 0.0
    assert not found, found


def test_the_kernel_that_ran_is_reported_and_a_missing_numba_is_named(monkeypatch):
    """result.kernel says which step ran; asked for "fused" without numba, the torch step runs with one
    warning naming it and how to get the fast one."""
    import importlib
    import warnings

    from torchslide.solver import fused_cpu

    sim = importlib.import_module("torchslide.solver.simulate")

    dem, rel, _ = _channel()
    r = simulate(dem, rel, Params.make(mu=0.2, xi=800.0), t_end=1.0)
    assert r.kernel == "fused-cpu"
    assert simulate(dem, rel, Params.make(mu=0.2, xi=800.0), t_end=1.0,
                    config=SolverConfig(kernel="eager")).kernel == "eager"
    monkeypatch.setattr(fused_cpu, "numba", None)
    monkeypatch.setattr(sim, "_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = simulate(dem, rel, Params.make(mu=0.2, xi=800.0), t_end=1.0)
    assert r.kernel == "eager"
    msgs = [str(w.message) for w in caught if "fused CPU step" in str(w.message)]
    assert len(msgs) == 1 and "pip install numba" in msgs[0] and "torch step" in msgs[0]


def test_the_fused_step_runs_on_the_processs_threads():
    """A process with OMP_NUM_THREADS=1 (as the harness's and Dask's workers run) gives the fused step one
    numba thread on a machine with more: N worker processes never start N x cores threads."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np, numba\n"
            "from torchslide.solver import simulate\nfrom torchslide.physics import Params\n"
            "from torchslide.terrain.grid import DEM\n"
            "x = np.arange(12) * 10.0\ndem = DEM(np.tile(-0.5 * x, (8, 1)), 10.0)\nrel = np.zeros(dem.shape)\n"
            "rel[3:5, 2:4] = 2.0\nr = simulate(dem, rel, Params.make(mu=0.2, xi=500.0), t_end=2.0)\n"
            "print(r.kernel, numba.get_num_threads())\n")
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="2")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["fused-cpu", "1"]
