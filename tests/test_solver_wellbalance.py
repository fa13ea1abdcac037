"""Verification case 1-3 (docs/verification.md): lake at rest, static pile (no creep), uniform slope, Voellmy terminal velocity."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import DEM

from .conftest import cap_release, plane_dem

G = 9.81


@pytest.mark.parametrize("slope_correction", [False, True])
def test_lake_at_rest_rough_bed(slope_correction):
    """Case 1: a frictionless lake over a rough DEM stays at rest to round-off (1000 steps)."""
    rng = np.random.default_rng(0)
    n, dx = 16, 1.0
    x = (np.arange(n) + 0.5) * dx
    X, Y = np.meshgrid(x, x)
    z = 2.0 * np.sin(X / 3.0) * np.cos(Y / 4.0) + 0.1 * rng.standard_normal((n, n))
    dem = DEM(z, dx)
    h = 8.0 - z
    assert h.min() > 0
    cfg = SolverConfig(no_creep=False, slope_correction=slope_correction, stop_ke_fraction=0.0,
                       output_interval=100.0, check_every=50)
    # dt ~ cfl dx / (2 sqrt(g h_max)); choose t_end for > 1000 steps
    dt_est = cfg.cfl * dx / (2 * math.sqrt(G * h.max()))
    r = simulate(dem, h, Params.make(mu=1e-12), t_end=1050 * dt_est, config=cfg)
    assert int(r.steps[0]) >= 1000
    speed = r.v_max[0]
    assert float(speed.max()) < 1e-10
    assert torch.allclose(r.h_final[0], torch.as_tensor(h), rtol=0, atol=1e-10)


def _com_x(h: torch.Tensor, dem: DEM) -> float:
    X = torch.as_tensor(dem.x_centres(), dtype=h.dtype)
    return float((h.sum(0) * X).sum() / h.sum())


def test_static_pile_no_creep():
    """Case 1: a pile on a slope with tan(theta) < mu does not creep (< half a cell in 100 s),
    and the result does not depend on the end time."""
    dx = 5.0
    dem = plane_dem(40, 30, dx, tan_theta=0.2)
    rel = cap_release(dem, 100.0, 75.0, 40.0, 10.0)  # edge slopes 0.5 + bed 0.2 > mu: the rim slumps
    p = Params.make(mu=0.45)
    cfg = SolverConfig(output_interval=10.0)
    r100 = simulate(dem, rel, p, t_end=100.0, config=cfg)
    r50 = simulate(dem, rel, p, t_end=50.0, config=cfg)
    drift = _com_x(r100.h_final[0], dem) - _com_x(torch.as_tensor(rel), dem)
    assert abs(drift) < 0.5 * dx
    assert bool(r100.stopped[0]) and float(r100.t_final[0]) < 50.0
    assert torch.equal(r100.h_final, r50.h_final)
    # the pile slumped a little (the rule does not freeze a pile that friction cannot hold)
    assert float(r100.v_max.max()) > 0.0


@pytest.mark.parametrize("h0,dx", [(0.1, 1.0), (2.0, 10.0), (20.0, 50.0)])
def test_uniform_slope_acceleration(h0, dx):
    """Case 2: a uniform layer accelerates at a = g cos(theta) (tan(theta) - mu) to 1e-6."""
    tan_t, mu = 0.5, 0.2
    dem = plane_dem(12, 5, dx, tan_theta=tan_t)
    t_end = 3.0
    r = simulate(dem, np.full(dem.shape, h0), Params.make(mu=mu), t_end=t_end,
                 config=SolverConfig(output_interval=0.5, boundary="open"),   # an infinite plane
                 gauges=[("c", 6 * dx, 2.5 * dx)])
    a = G * math.cos(math.atan(tan_t)) * (tan_t - mu)
    g = r.gauges["c"]
    u_ref = a * g.t
    rel_err = (g.u[0, 1:] - u_ref[1:]).abs() / u_ref[1:]
    assert float(rel_err.max()) < 1e-6
    assert float(g.v.abs().max()) < 1e-12
    # every cell accelerates the same (open boundaries keep the uniform state)
    assert float((r.v_max[0] - a * t_end).abs().max()) < 1e-6 * a * t_end


def test_voellmy_terminal_velocity():
    """Case 3: u(t) = U tanh(g t (sin - mu cos) / U), U^2 = xi h (sin - mu cos)."""
    tan_t, mu, xi, h0, dx = 0.5, 0.2, 500.0, 1.0, 5.0
    th = math.atan(tan_t)
    dem = plane_dem(10, 5, dx, tan_theta=tan_t)
    t_end = 40.0
    r = simulate(dem, np.full(dem.shape, h0), Params.make(mu=mu, xi=xi), t_end=t_end,
                 config=SolverConfig(output_interval=1.0, boundary="open"),   # an infinite plane
                 gauges=[("c", 25.0, 12.5)])
    s = math.sin(th) - mu * math.cos(th)
    U = math.sqrt(xi * h0 * s)
    g = r.gauges["c"]
    u_ref = U * torch.tanh(G * g.t * s / U)
    # steady state (robust check); tanh(g t s / U) at t_end differs from 1 by < 1e-7
    assert abs(float(g.u[0, -1]) - U) / U < 1e-6
    # transient: the implicit friction step is first order in dt (dt ~ 0.13 s here, relaxation time
    # U / (2 g s) ~ 2.2 s), so a few per cent at most
    assert float((g.u[0] - u_ref).abs().max()) / U < 0.03
