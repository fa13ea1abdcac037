"""Terrain fields of a DEM: gradient, slope angle, unit normal, curvature, hillshade.

Every function takes either a :class:`DEM` or an elevation array ``z`` (ny, nx) (numpy array or
torch tensor; a torch input gives torch outputs on the same device/dtype) plus ``cellsize`` (m).
Row 0 is the southern row, so d/dy is along the row index and d/dx along the column index.
Derivatives are second-order central differences inside and first-order one-sided at the edges
(``numpy.gradient`` / ``torch.gradient``).

Notation (Zevenbergen & Thorne 1987): p = dz/dx, q = dz/dy, r = d2z/dx2, s = d2z/dxdy, t = d2z/dy2.
"""
from __future__ import annotations

import math

import numpy as np

from .grid import DEM

__all__ = [
    "gradient",
    "slope",
    "slope_deg",
    "unit_normal",
    "second_derivatives",
    "curvature",
    "profile_curvature",
    "plan_curvature",
    "hillshade",
]


def _z_cs(z, cellsize):
    if isinstance(z, DEM):
        return z.z, z.cellsize
    if cellsize is None:
        raise ValueError("cellsize (m) is required when z is an array; or pass a DEM")
    return z, float(cellsize)


def _is_torch(a) -> bool:
    try:
        import torch
    except ImportError:  # pragma: no cover
        return False
    return isinstance(a, torch.Tensor)


def _lib(a):
    if _is_torch(a):
        import torch

        return torch
    return np


def _grad2(a, cs):
    """(d/dx, d/dy) of a (ny, nx) array: x along columns (dim -1), y along rows (dim -2)."""
    if _is_torch(a):
        import torch

        dy, dx = torch.gradient(a, spacing=cs, dim=(-2, -1))
        return dx, dy
    dy, dx = np.gradient(np.asarray(a, dtype=np.float64), cs)
    return dx, dy


def gradient(z, cellsize: float | None = None):
    """Surface gradient (p, q) = (dz/dx, dz/dy), each (ny, nx), dimensionless (m/m)."""
    z, cs = _z_cs(z, cellsize)
    return _grad2(z, cs)


def slope(z, cellsize: float | None = None):
    """Slope angle theta = atan(|grad z|), (ny, nx), radians."""
    p, q = gradient(z, cellsize)
    lib = _lib(p)
    return lib.arctan(lib.sqrt(p**2 + q**2))


def slope_deg(z, cellsize: float | None = None):
    """Slope angle in degrees, (ny, nx)."""
    return slope(z, cellsize) * (180.0 / math.pi)


def unit_normal(z, cellsize: float | None = None):
    """Upward unit normal (nx, ny, nz) = (-p, -q, 1) / sqrt(1 + p^2 + q^2), each (ny, nx).

    nz = cos(theta), the factor that turns g into the bed-normal gravity g_n = g cos(theta).
    """
    p, q = gradient(z, cellsize)
    lib = _lib(p)
    w = 1.0 / lib.sqrt(1.0 + p**2 + q**2)
    return -p * w, -q * w, w


def second_derivatives(z, cellsize: float | None = None):
    """(r, s, t) = (d2z/dx2, d2z/dxdy, d2z/dy2), each (ny, nx), 1/m."""
    z, cs = _z_cs(z, cellsize)
    p, q = _grad2(z, cs)
    r, s1 = _grad2(p, cs)
    s2, t = _grad2(q, cs)
    return r, 0.5 * (s1 + s2), t


def curvature(z, cellsize: float | None = None, eps: float = 1e-12):
    """Profile and plan curvature (k_profile, k_plan), each (ny, nx), 1/m.

    k_profile = -(p^2 r + 2 p q s + q^2 t) / ((p^2 + q^2) (1 + p^2 + q^2)^(3/2))
        curvature of the normal section along the steepest-descent direction;
    k_plan    = -(q^2 r - 2 p q s + p^2 t) / (p^2 + q^2)^(3/2)
        curvature of the contour line.
    Sign: positive = convex (a hill top, a break to steeper ground; divergent contours),
    negative = concave (a valley floor, a slope foot; convergent contours). Both are 0 where the
    surface is flat (p^2 + q^2 < eps), where they are undefined.
    """
    z, cs = _z_cs(z, cellsize)
    p, q = _grad2(z, cs)
    r, s, t = second_derivatives(z, cs)
    lib = _lib(p)
    g2 = p**2 + q**2
    flat = g2 < eps
    g2s = lib.where(flat, lib.ones_like(g2), g2)
    kp = -(p**2 * r + 2 * p * q * s + q**2 * t) / (g2s * (1.0 + g2) ** 1.5)
    kh = -(q**2 * r - 2 * p * q * s + p**2 * t) / g2s**1.5
    zero = lib.zeros_like(g2)
    return lib.where(flat, zero, kp), lib.where(flat, zero, kh)


def profile_curvature(z, cellsize: float | None = None):
    """Profile curvature, (ny, nx), 1/m (see :func:`curvature`)."""
    return curvature(z, cellsize)[0]


def plan_curvature(z, cellsize: float | None = None):
    """Plan (contour) curvature, (ny, nx), 1/m (see :func:`curvature`)."""
    return curvature(z, cellsize)[1]


def hillshade(z, cellsize: float | None = None, azimuth_deg: float = 315.0, altitude_deg: float = 45.0,
              z_factor: float = 1.0) -> np.ndarray:
    """Hillshade in [0, 1], (ny, nx) numpy, for figures (light from ``azimuth_deg`` clockwise from north).

    Plot with ``imshow(hs, origin="lower", cmap="gray", extent=dem.extent-as-(xmin, xmax, ymin, ymax))``.
    """
    z, cs = _z_cs(z, cellsize)
    if _is_torch(z):
        z = z.detach().cpu().double().numpy()
    p, q = _grad2(np.asarray(z, dtype=np.float64) * z_factor, cs)
    az = math.radians(azimuth_deg)
    alt = math.radians(altitude_deg)
    # light direction (east, north, up)
    lx, ly, lz = math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)
    n = 1.0 / np.sqrt(1.0 + p**2 + q**2)
    hs = (-p * lx - q * ly + lz) * n
    return np.clip(hs, 0.0, 1.0)
