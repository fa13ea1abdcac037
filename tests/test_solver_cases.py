"""Shared small terrains for the solver tests (plus a smoke test of the shared cases)."""
from __future__ import annotations

import numpy as np
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import DEM


def plane_dem(nx: int, ny: int, dx: float, tan_theta: float) -> DEM:
    """z = -x tan(theta) (flow towards +x)."""
    x = (np.arange(nx) + 0.5) * dx
    return DEM(np.tile(-x * tan_theta, (ny, 1)), dx)


def chute_dem(nx: int = 60, ny: int = 24, dx: float = 10.0, slope_deg: float = 30.0, x_break: float = 300.0) -> DEM:
    """Inclined plane that turns into a flat run-out at x_break, with a gentle lateral trough."""
    x = (np.arange(nx) + 0.5) * dx
    y = (np.arange(ny) + 0.5) * dx
    zx = np.where(x < x_break, (x_break - x) * np.tan(np.radians(slope_deg)), 0.0)
    yc = y - y.mean()
    return DEM(zx[None, :] + 0.002 * yc[:, None] ** 2, dx)


def cap_release(dem: DEM, xc: float, yc: float, radius: float, height: float) -> np.ndarray:
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    return np.clip(height * (1 - ((X - xc) ** 2 + (Y - yc) ** 2) / radius**2), 0, None)


def chute_case():
    dem = chute_dem()
    rel = cap_release(dem, 120.0, 120.0, 50.0, 8.0)
    return dem, rel


def test_chute_smoke():
    dem, rel = chute_case()
    r = simulate(dem, rel, Params.make(mu=0.3, xi=500.0), t_end=120.0)
    assert not bool(r.failed.any())
    assert bool(r.stopped.all())
    # the deposit lies beyond the slope break, the release area is (mostly) left behind
    X = torch.as_tensor(dem.x_centres())
    com = float((r.h_final[0].sum(0) * X).sum() / r.h_final[0].sum())
    assert com > 250.0
