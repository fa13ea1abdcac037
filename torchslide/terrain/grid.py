"""The DEM grid: cell-centred elevations on a regular square grid in map coordinates.

Conventions used everywhere in torchslide:

* ``z`` has shape (ny, nx), metres, float64, all finite. Row 0 is the *southern* row: the map
  coordinate y grows with the row index and x with the column index (ESRI ASCII files store the
  northern row first; the readers and writers flip).
* ``cellsize`` is the side of a square cell in metres.
* ``xll, yll`` are the map coordinates (m) of the lower-left corner of the lower-left cell
  (ESRI ``xllcorner`` / ``yllcorner``). Cell (i, j) has its centre at
  ``x = xll + (j + 0.5) * cellsize``, ``y = yll + (i + 0.5) * cellsize``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class TerrainError(ValueError):
    """Bad terrain or release input; the message names the field and the value."""


@dataclass
class DEM:
    """A digital elevation model on a regular grid.

    Attributes:
        z: (ny, nx) elevation, m, finite everywhere.
        cellsize: cell side, m (> 0).
        xll, yll: lower-left corner of the grid in map coordinates, m.
        crs: optional coordinate reference system (WKT or EPSG string), carried through I/O.
    """

    z: np.ndarray
    cellsize: float
    xll: float = 0.0
    yll: float = 0.0
    crs: str | None = field(default=None, repr=False)
    outside: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.z = np.asarray(self.z, dtype=np.float64)
        if self.z.ndim != 2 or min(self.z.shape) < 3:
            raise TerrainError(f"DEM z must be a 2-D array of at least 3 x 3 cells, got shape {self.z.shape}")
        if not (np.isfinite(self.cellsize) and self.cellsize > 0):
            raise TerrainError(f"DEM cellsize must be a positive number of metres, got {self.cellsize!r}")
        self.cellsize = float(self.cellsize)
        bad = ~np.isfinite(self.z)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            x, y = self.cell_centre(int(i), int(j))
            raise TerrainError(
                f"DEM z has {int(bad.sum())} non-finite (NaN/nodata) cells inside the domain, "
                f"first at row {i}, col {j} (x={x:.1f} m, y={y:.1f} m)"
            )
        if self.outside is not None:
            self.outside = np.asarray(self.outside, dtype=bool)
            if self.outside.shape != self.z.shape:
                raise TerrainError(f"DEM outside mask has shape {self.outside.shape}, the grid is {self.z.shape}")
            if self.outside.all():
                raise TerrainError("DEM: every cell is outside the domain (nodata)")
            if not self.outside.any():
                self.outside = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.z.shape  # type: ignore[return-value]

    @property
    def ny(self) -> int:
        return self.z.shape[0]

    @property
    def nx(self) -> int:
        return self.z.shape[1]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the grid's outer edges, m."""
        return (self.xll, self.yll, self.xll + self.nx * self.cellsize, self.yll + self.ny * self.cellsize)

    def cell_centre(self, i: int, j: int) -> tuple[float, float]:
        """Map coordinates (x, y) in m of the centre of cell (row i, column j)."""
        return self.xll + (j + 0.5) * self.cellsize, self.yll + (i + 0.5) * self.cellsize

    def x_centres(self) -> np.ndarray:
        """(nx,) x of cell centres, m."""
        return self.xll + (np.arange(self.nx) + 0.5) * self.cellsize

    def y_centres(self) -> np.ndarray:
        """(ny,) y of cell centres, m."""
        return self.yll + (np.arange(self.ny) + 0.5) * self.cellsize

    def contains(self, x: float, y: float) -> bool:
        xmin, ymin, xmax, ymax = self.extent
        return bool(xmin <= x < xmax and ymin <= y < ymax)

    def index(self, x: float, y: float, what: str = "point") -> tuple[int, int]:
        """(row i, column j) of the cell containing map point (x, y).

        Raises TerrainError naming ``what`` and the coordinates when the point is outside the DEM.
        """
        if not (np.isfinite(x) and np.isfinite(y)) or not self.contains(x, y):
            xmin, ymin, xmax, ymax = self.extent
            raise TerrainError(
                f"{what} at x={x}, y={y} is outside the DEM (x in [{xmin:.1f}, {xmax:.1f}), "
                f"y in [{ymin:.1f}, {ymax:.1f}))"
            )
        j = int((x - self.xll) // self.cellsize)
        i = int((y - self.yll) // self.cellsize)
        return i, j

    def surface_area(self) -> np.ndarray:
        """(ny, nx) surface area of each cell, m^2: cellsize^2 / cos(theta) = cellsize^2 sqrt(1 + |grad z|^2),
        the slope from central differences (one-sided at the edges), as the solver measures it. A
        thickness normal to the slope times this is a volume."""
        gy, gx = np.gradient(self.z, self.cellsize) if min(self.shape) > 1 else (np.zeros(self.shape),) * 2
        return self.cellsize**2 * np.sqrt(1.0 + gx * gx + gy * gy)

    def same_grid(self, other: "DEM", rtol: float = 1e-9) -> bool:
        """True when ``other`` has the same shape, cell size and origin."""
        return (
            self.shape == other.shape
            and abs(self.cellsize - other.cellsize) <= rtol * self.cellsize
            and abs(self.xll - other.xll) <= 1e-6 * self.cellsize
            and abs(self.yll - other.yll) <= 1e-6 * self.cellsize
        )


def same_crs(a: str | None, b: str | None) -> bool:
    """Whether two CRS descriptions (WKT, "EPSG:n", PROJ) name the same system; True when one is unknown."""
    if not a or not b:
        return True
    try:
        from rasterio.crs import CRS

        return CRS.from_user_input(a) == CRS.from_user_input(b)
    except Exception:
        return a == b
