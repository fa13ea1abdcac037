"""Verification cases 1-3 (docs/verification.md) as a user sets them up: on a DEM of the tilted plane
in map coordinates, at several slope angles and plan orientations that are not aligned with the grid.

References in slope coordinates (x along the surface, h normal to it) map to the DEM with
x_map = x cos(theta); a horizontal velocity is the surface velocity times cos(theta) along the dip."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import DEM

from .conftest import cap_release, plane_dem, tilted_plane

G = 9.81
ANGLES = [(22.0, 0.0), (35.0, 0.0), (50.0, 0.0), (35.0, 30.0), (50.0, 120.0)]


def test_lake_at_rest_rough_bed():
    """Case 1: a frictionless lake over a rough DEM stays at rest to round-off (1000 steps), with the
    hydrostatic pressure of a fluid (slope_correction=False: the classic shallow-water equations)."""
    rng = np.random.default_rng(0)
    n, dx = 16, 1.0
    x = (np.arange(n) + 0.5) * dx
    X, Y = np.meshgrid(x, x)
    z = 2.0 * np.sin(X / 3.0) * np.cos(Y / 4.0) + 0.1 * rng.standard_normal((n, n))
    dem = DEM(z, dx)
    h = 8.0 - z
    assert h.min() > 0
    cfg = SolverConfig(no_creep=False, slope_correction=False, stop_ke_fraction=0.0,
                       output_interval=100.0, check_every=50)
    dt_est = cfg.cfl * dx / (2 * math.sqrt(G * h.max()))
    r = simulate(dem, h, Params.make(mu=1e-12), t_end=1050 * dt_est, config=cfg, thickness="vertical")
    assert int(r.steps[0]) >= 1000
    assert float(r.v_max[0].max()) < 1e-10
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


@pytest.mark.parametrize("plan", [0.0, 30.0, 45.0])
def test_a_layer_starts_exactly_when_the_slope_beats_friction_in_any_plan_orientation(plan):
    """Onset along the surface: a uniform layer on a 25 degree plane stays at rest for mu just above
    tan(theta) and moves for mu just below, whatever the plane's orientation on the grid (friction on
    the horizontal momentum instead of the momentum along the surface would hold it up to
    tan(theta) = mu / cos(theta))."""
    tan_t = math.tan(math.radians(25.0))
    dem, *_ = tilted_plane(10, 5.0, 25.0, plan)
    for mu, moves in ((tan_t * 1.02, False), (tan_t * 0.98, True)):
        r = simulate(dem, np.full(dem.shape, 1.0), Params.make(mu=mu), t_end=2.0,
                     config=SolverConfig(output_interval=1.0, boundary="open"))
        assert (float(r.v_max.max()) > 0.01) == moves, (mu, moves)


@pytest.mark.parametrize("theta,plan", ANGLES)
@pytest.mark.parametrize("h0,dx", [(0.1, 1.0), (2.0, 10.0)])
def test_uniform_slope_acceleration_in_map_coordinates(theta, plan, h0, dx):
    """Case 2: a uniform layer (h0 normal to the slope) accelerates along the surface at
    g (sin - mu cos), i.e. horizontally at g cos(theta) (sin(theta) - mu cos(theta)), to 1e-6; its
    thickness stays h0 and its horizontal velocity points down the dip."""
    th, mu, t_end = math.radians(theta), 0.2, 2.0
    dem, *_ = tilted_plane(10, dx, theta, plan)
    r = simulate(dem, np.full(dem.shape, h0), Params.make(mu=mu), t_end=t_end,
                 config=SolverConfig(output_interval=0.5, boundary="open"), gauges=[("c", 0.3 * dx, 0.2 * dx)])
    g = r.gauges["c"]
    a_s = G * (math.sin(th) - mu * math.cos(th))
    u_h = torch.sqrt(g.u**2 + g.v**2)[0, 1:]
    assert float(((u_h - a_s * math.cos(th) * g.t[1:]).abs() / (a_s * math.cos(th) * g.t[1:])).max()) < 1e-6
    assert float(((g.speed[0, 1:] - a_s * g.t[1:]).abs() / (a_s * g.t[1:])).max()) < 1e-6
    a = math.radians(plan)
    assert float((g.u[0, -1] * math.sin(a) - g.v[0, -1] * math.cos(a)).abs()) < 1e-9 * float(u_h[-1])
    assert float((g.h[0] - h0).abs().max()) < 1e-9 * h0
    assert float((r.v_max[0] - a_s * t_end).abs().max()) < 1e-6 * a_s * t_end


@pytest.mark.parametrize("theta,plan", ANGLES)
def test_release_volume_is_normal_thickness_times_surface_area(theta, plan):
    """A 1 m release (normal to the slope, the default) holds 1 m x its surface area (map area /
    cos theta); given as vertical thickness it holds 1 m x its map area."""
    dem, *_ = tilted_plane(8, 5.0, theta, plan)
    rel = np.ones(dem.shape)
    cfg = SolverConfig(output_interval=0.5, boundary="open")
    surface = 64 * 25.0 / math.cos(math.radians(theta))
    r = simulate(dem, rel, Params.make(mu=0.2), t_end=0.5, config=cfg)
    assert abs(float(r.release_volume[0]) - surface) < 1e-9 * surface
    assert abs(float((r.h_final[0] * r.cell_area).sum()) - float(r.final_volume[0])) < 1e-9 * surface
    rv = simulate(dem, rel, Params.make(mu=0.2), t_end=0.5, config=cfg, thickness="vertical")
    assert abs(float(rv.release_volume[0]) - 64 * 25.0) < 1e-9 * surface


@pytest.mark.parametrize("theta,plan", [(22.0, 0.0), (35.0, 30.0), (50.0, 0.0)])
def test_voellmy_terminal_velocity_along_the_surface(theta, plan):
    """Case 3: |V|(t) = U tanh(g t (sin - mu cos) / U), U^2 = xi h (sin - mu cos), h normal to the slope."""
    th, mu, xi, h0, dx = math.radians(theta), 0.2, 500.0, 1.0, 5.0
    dem, *_ = tilted_plane(8, dx, theta, plan)
    r = simulate(dem, np.full(dem.shape, h0), Params.make(mu=mu, xi=xi), t_end=60.0,
                 config=SolverConfig(output_interval=1.0, boundary="open"), gauges=[("c", 1.0, 1.0)])
    s = math.sin(th) - mu * math.cos(th)
    U = math.sqrt(xi * h0 * s)
    g = r.gauges["c"]
    assert abs(float(g.speed[0, -1]) - U) / U < 1e-6
    # transient: the implicit friction step is first order in dt, so a few per cent at most
    u_ref = U * torch.tanh(G * g.t * s / U)
    assert float((g.speed[0] - u_ref).abs().max()) / U < 0.03
