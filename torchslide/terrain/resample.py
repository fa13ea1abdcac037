"""Resampling a DEM and the rasters on its grid to the inversion grid (``[terrain] cellsize``).

The new grid covers the DEM's extent with square cells of the new size from the same lower-left corner
(cells that would stick out are dropped). Elevations are interpolated bilinearly at the new cell
centres (scipy.interpolate.RegularGridInterpolator; nearest cell centres at the rim). A new cell is
outside the domain when its centre's nearest source cell is. Thickness fields (release, erodible depth)
are interpolated the same way and then scaled so that they hold the volume they held on the source grid.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from .grid import DEM, TerrainError

__all__ = ["resample_dem", "resample_thickness"]


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
