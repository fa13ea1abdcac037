"""Resampling a DEM and the rasters on its grid to the inversion grid (``[terrain] cellsize``).

The new grid covers the DEM's extent with square cells of the new size from the same lower-left corner
(cells that would stick out are dropped). Elevations are interpolated bilinearly at the new cell
centres (scipy.interpolate.RegularGridInterpolator; nearest cell centres at the rim). A new cell is
outside the domain when its centre's nearest source cell is. Thickness fields (release, erodible depth)
are interpolated the same way and then scaled so that they hold the volume they held on the source grid.
Recorded maps (deposit depth, elevation change, impact) are averaged over the source cells each new cell
overlaps, weighted by the overlapping area (:func:`resample_map`).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from .grid import DEM, TerrainError

__all__ = ["resample_dem", "resample_thickness", "resample_map", "overlap_weights"]


def _target(src: DEM, cellsize: float) -> tuple[int, int]:
    ny = int(np.floor(src.ny * src.cellsize / cellsize + 1e-9))
    nx = int(np.floor(src.nx * src.cellsize / cellsize + 1e-9))
    if min(ny, nx) < 3:
        raise TerrainError(f"cellsize {cellsize:g} m leaves fewer than 3 x 3 cells of the "
                           f"{src.nx * src.cellsize:g} x {src.ny * src.cellsize:g} m DEM")
    return ny, nx


def _sample(a: np.ndarray, src: DEM, dst_x: np.ndarray, dst_y: np.ndarray, method: str) -> np.ndarray:
    f = RegularGridInterpolator((src.y_centres(), src.x_centres()), a, method=method, bounds_error=False, fill_value=None)
    Y, X = np.meshgrid(np.clip(dst_y, src.y_centres()[0], src.y_centres()[-1]),
                       np.clip(dst_x, src.x_centres()[0], src.x_centres()[-1]), indexing="ij")
    return f(np.stack([Y, X], axis=-1))


def resample_dem(src: DEM, cellsize: float) -> DEM:
    """``src`` on square cells of ``cellsize`` m (the same corner and CRS; see the module docstring)."""
    if not (np.isfinite(cellsize) and cellsize > 0):
        raise TerrainError(f"cellsize must be a positive number of metres, got {cellsize!r}")
    if abs(cellsize - src.cellsize) <= 1e-9 * src.cellsize:
        return src
    ny, nx = _target(src, cellsize)
    xs = src.xll + (np.arange(nx) + 0.5) * cellsize
    ys = src.yll + (np.arange(ny) + 0.5) * cellsize
    z = _sample(src.z, src, xs, ys, "linear")
    outside = None
    if src.outside is not None:
        outside = _sample(src.outside.astype(np.float64), src, xs, ys, "nearest") > 0.5
    return DEM(z=z, cellsize=float(cellsize), xll=src.xll, yll=src.yll, crs=src.crs, outside=outside)


def resample_thickness(a: np.ndarray, src: DEM, dst: DEM, area_src: np.ndarray, area_dst: np.ndarray) -> np.ndarray:
    """A thickness field (ny, nx) of ``src``'s grid on ``dst``'s grid, scaled to keep its volume
    sum(a * area) (``area_*``: the cell areas that turn the thickness into a volume on each grid)."""
    if dst is src:
        return a
    out = np.clip(_sample(np.asarray(a, dtype=np.float64), src, dst.x_centres(), dst.y_centres(), "linear"), 0.0, None)
    v_src, v_dst = float((a * area_src).sum()), float((out * area_dst).sum())
    if v_src > 0 and v_dst <= 0:
        raise TerrainError(f"the field covers no cell centre of the {dst.cellsize:g} m grid; use smaller cells")
    return out * (v_src / v_dst) if v_dst > 0 else out


def overlap_weights(n_dst: int, cs_dst: float, n_src: int, cs_src: float, offset: float = 0.0) -> np.ndarray:
    """(n_dst, n_src) length of the overlap of each destination cell [i cs_dst, (i + 1) cs_dst) with each
    source cell [offset + j cs_src, offset + (j + 1) cs_src) along one axis, m (``offset``: the source
    grid's origin minus the destination's)."""
    a0 = np.arange(n_dst)[:, None] * cs_dst
    b0 = offset + np.arange(n_src)[None, :] * cs_src
    return np.clip(np.minimum(a0 + cs_dst, b0 + cs_src) - np.maximum(a0, b0), 0.0, None)


def resample_map(a: np.ndarray, src: DEM, dst: DEM, binary: bool = False, min_mapped: float = 0.5) -> np.ndarray:
    """A recorded map (ny, nx) of ``src``'s grid (NaN: not mapped) on ``dst``'s grid: each new cell the
    area-weighted mean of the mapped source cells it overlaps, NaN where they cover less than
    ``min_mapped`` of it; ``binary`` (an impact map of 0 and 1): that mean rounded (>= 0.5 -> 1)."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape != src.shape:
        raise TerrainError(f"map has shape {a.shape}, its grid is {src.shape}")
    wy = overlap_weights(dst.ny, dst.cellsize, src.ny, src.cellsize, src.yll - dst.yll)
    wx = overlap_weights(dst.nx, dst.cellsize, src.nx, src.cellsize, src.xll - dst.xll)
    mapped = np.isfinite(a)
    covered = wy @ mapped.astype(np.float64) @ wx.T
    total = wy @ np.where(mapped, a, 0.0) @ wx.T
    with np.errstate(invalid="ignore", divide="ignore"):
        out = total / covered
    out[covered < min_mapped * dst.cellsize ** 2] = np.nan
    if binary:
        out = np.where(np.isfinite(out), (out >= 0.5).astype(np.float64), np.nan)
    return out
