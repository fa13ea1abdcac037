"""Solver robustness: every allowed limiter / Courant setting, both precisions, every candidate term and
extreme (mu, xi) run without a failed member and close the mass balance (release + entrained = final +
outflow). The default suite runs one chute; the slow suite sweeps the harness terrains as well."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate

from .conftest import cap_release, chute_dem

# six members: low / mid / high mu against a short and a long xi, each with other candidate terms on
MEMBERS = dict(mu=[0.05, 0.05, 0.25, 0.25, 0.6, 0.6], xi=[100.0, 2000.0] * 3, kappa=[0.0, 0.005] * 3,
               tau_y=[0.0, 0.0, 5.0, 0.0, 0.0, 20.0], curvature=[0.0, 1.0] * 3,
               earth_pressure=[0.0, 0.0, 1.0, 1.0, 0.5, 0.0], phi_int=[35.0] * 6, mu_i=[0.0, 0.3, 0.0, 0.0, 0.3, 0.0])
TOL = {torch.float32: 1e-4, torch.float64: 1e-9}


def check_members(dem, rel, erod, theta, cfl, dtype, t_end):
    """Run MEMBERS once; return a list of the problems found (empty: every member fine)."""
    p = Params.make(**{k: np.array(v, dtype=float) for k, v in MEMBERS.items()})
    r = simulate(dem, rel, p, t_end=t_end, config=SolverConfig(cfl=cfl, limiter_theta=theta, output_interval=5.0),
                 erodible_depth=erod, dtype=dtype)
    bad = []
    for b in range(len(MEMBERS["mu"])):
        rv = float(r.release_volume[b] if r.release_volume.dim() else r.release_volume)
        err = (float(r.final_volume[b]) + float(r.outflow_volume[b]) - float(r.entrained_volume[b]) - rv) / rv
        if bool(r.failed[b]) or not torch.isfinite(r.h_final[b]).all() or abs(err) > TOL[dtype]:
            bad.append((theta, cfl, str(dtype), b, r.failure_reason[b] if r.failure_reason else "", err))
    return bad


@pytest.mark.parametrize("theta, dtype", [(1.0, torch.float32), (2.0, torch.float64), (2.0, torch.float32)])
def test_chute_runs_at_the_limits_of_the_settings(theta, dtype):
    dem = chute_dem(nx=60, ny=24, dx=10.0)
    rel = cap_release(dem, 120.0, 120.0, 50.0, 8.0)
    assert check_members(dem, rel, np.full(dem.z.shape, 2.0), theta, 0.9, dtype, t_end=60.0) == []


@pytest.mark.slow
def test_robustness_sweep():
    """The full sweep (about 20 min on 2 cores): harness terrains at 40 and 20 m, a 10 m chute and a
    45-degree 5 m chute; limiter_theta 1 and 2, cfl 0.25, 0.45 and 0.9, float32 and float64."""
    from experiments.hidden_physics import scenarios

    cases = []
    for terr in ("resolved", "narrow"):
        with scenarios.terrain_variant(terr):
            for cs in (40.0, 20.0):
                dem, erod = scenarios.terrain(cs)
                cases.append((dem, scenarios.release(dem, scenarios.V_NOMINAL), erod))
    for dx, nx, ny, slope in ((10.0, 60, 24, 30.0), (5.0, 120, 48, 45.0)):
        dem = chute_dem(nx=nx, ny=ny, dx=dx, slope_deg=slope)
        cases.append((dem, cap_release(dem, 120.0, 120.0, 50.0, 8.0), np.full(dem.z.shape, 2.0)))
    bad = []
    for (dem, rel, erod), theta, cfl, dtype in itertools.product(cases, (1.0, 2.0), (0.25, 0.45, 0.9),
                                                                  (torch.float32, torch.float64)):
        bad += check_members(dem, rel, erod, theta, cfl, dtype, t_end=120.0)
    assert bad == []
