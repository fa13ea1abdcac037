"""Terrain: the DEM grid type, raster I/O, slope/normal/curvature fields, synthetic terrains, releases."""
from .grid import DEM, TerrainError

__all__ = ["DEM", "TerrainError"]
